"""Shadows: shadow maps rendered from lights, PCF/PCSS soft shadows, heightfield ray marching,
horizon maps. One private module per technique; public names re-exported here."""
