"""System packages: loading the model files with located errors, cross-reference
validation, and importing a package's own Python modules."""
