"""Simulations that feed the renderer: ripple and dune automata, sand dust, fire, cloth."""
