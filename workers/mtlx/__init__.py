"""The procedural MaterialX export: a node library (nodedefs with our own GLSL code) and the mapping of a material
graph onto it, so that a fitted material stays procedural in renderers that read MaterialX."""
