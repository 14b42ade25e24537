"""PPTBF generator, descriptors and the PPTBF feature database."""
