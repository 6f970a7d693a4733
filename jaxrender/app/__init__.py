"""The orchestration layer: showcase scenes (`scenes`), the gallery (`gallery`) and the command
lines (`cli`). It is the only layer that composes the kernel packages `jaxrender`, `sims` and
`fitting`; no kernel module imports it (tests/test_architecture.py checks the import graph)."""
