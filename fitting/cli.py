"""`fitting` command line: BTF capture synthesis, fitting, pyramid, relighting and reports."""

from jaxrender._cli import run_cli

COMMANDS = {
    "synth": ("fitting._cmd_synth", "write a synthetic multi-light HDR capture with known parameter maps"),
    "fit": ("fitting._cmd_fit", "fit per-texel anisotropic BRDF parameters to a capture directory"),
    "pyramid": ("fitting._cmd_pyramid", "build the EM multi-resolution 2-lobe levels of a BTF"),
    "relight": ("fitting._cmd_relight", "render a fitted BTF under one distant light"),
    "report": ("fitting._cmd_report", "relighting error and residuals of a fit, as a figure and a table"),
}


def main(argv=None) -> int:
    return run_cli("fitting", __doc__.splitlines()[0], COMMANDS, argv)


if __name__ == "__main__":
    raise SystemExit(main())
