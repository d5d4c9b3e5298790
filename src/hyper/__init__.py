"""hyper: exercise-driven skeletal-muscle hypertrophy (Devold, Rognes & Rangamani 2026).

Signaling ODEs (IGF1-AKT-FOXO-mTOR) drive transversely isotropic growth of a
hyperelastic muscle solved with DOLFINx; the grown cross-section feeds back on
protein synthesis. See MODEL.md for the mathematics.
"""

__version__ = "0.1.0"
