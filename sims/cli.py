"""`sims` command line: the Nishimori-Ouchi ripple and dune automata."""

from jaxrender._cli import run_cli

COMMANDS = {
    "ripples": ("sims._cmd_ripples", "grow wind ripples with the saltation + creep automaton"),
    "dunes": ("sims._cmd_dunes", "grow dunes with the slope-dependent saltation automaton"),
}


def main(argv=None) -> int:
    return run_cli("sims", __doc__.splitlines()[0], COMMANDS, argv)


if __name__ == "__main__":
    raise SystemExit(main())
