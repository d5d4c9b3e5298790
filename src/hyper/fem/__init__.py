"""The finite-element layer (DOLFINx): geometry, sections, mechanics, growth field, coupled model, fibres, meshing."""
