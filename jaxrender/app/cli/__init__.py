"""The command lines `jaxrender`, `fitting` and `sims` (`programs`), one module per subcommand."""
