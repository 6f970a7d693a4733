"""`jaxrender` command line: a thin layer over the public API."""

from ._cli import run_cli

COMMANDS = {
    "gallery": ("jaxrender._cmd_gallery", "render the showcase scenes and a fit into an HTML gallery"),
    "shafts": ("jaxrender._cmd_shafts", "render light shafts from a scene file (paper 000)"),
    "desert": ("jaxrender._cmd_desert", "render a desert of dunes and wind ripples (paper 001)"),
    "noh": ("jaxrender._cmd_noh", "render woven fabric under environment light and firelight (paper 004)"),
}


def main(argv=None) -> int:
    return run_cli("jaxrender", __doc__.splitlines()[0], COMMANDS, argv)


if __name__ == "__main__":
    raise SystemExit(main())
