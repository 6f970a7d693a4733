"""Fitting anisotropic BTFs to HDR multi-light captures (paper 004, sections 3.1-3.2)."""
