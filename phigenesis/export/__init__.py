"""Exporters of Gaussian scenes to files other tools read (3D Gaussian Splatting PLY: :mod:`.ply`)."""
