"""Pipeline stages: pure numpy/torch code (no Ray, no SQLite, no file paths inside algorithms)."""
