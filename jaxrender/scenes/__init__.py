"""Scene files and the showcase scenes (stage, desert, Noh) used by the gallery and the CLIs."""
