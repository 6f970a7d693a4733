"""The console scripts `jaxrender`, `fitting` and `sims`: each a table of subcommands, each
subcommand a module of this package loaded by name only when asked for (so `--help` needs no jax).

`python -m jaxrender.app.cli.programs PROGRAM COMMAND ...` runs one without the console script.
"""

from __future__ import annotations

import sys

from .driver import run_cli

JAXRENDER_COMMANDS = {
    "gallery": ("jaxrender.app.cli.gallery", "render the showcase scenes and a fit into an HTML gallery"),
    "shafts": ("jaxrender.app.cli.shafts", "render light shafts from a scene file (paper 000)"),
    "desert": ("jaxrender.app.cli.desert", "render a desert of dunes and wind ripples (paper 001)"),
    "noh": ("jaxrender.app.cli.noh", "Takigi Noh: a costumed performer on a Noh stage between bonfires (paper 004)"),
}
FITTING_COMMANDS = {
    "synth": ("jaxrender.app.cli.synth", "write a synthetic multi-light HDR capture with known parameter maps"),
    "manifest": ("jaxrender.app.cli.manifest", "write a capture manifest (capture.json) from a CSV of images"),
    "ingest": ("jaxrender.app.cli.ingest", "merge a capture into an on-disk observation store in one streaming pass"),
    "fit": ("jaxrender.app.cli.fit", "fit per-texel anisotropic BRDF parameters to a capture directory or store"),
    "pyramid": ("jaxrender.app.cli.pyramid", "build the EM multi-resolution 2-lobe levels of a BTF"),
    "relight": ("jaxrender.app.cli.relight", "render a fitted BTF under one distant light"),
    "report": ("jaxrender.app.cli.report", "relighting error and residuals of a fit, as a figure and a table"),
    "evaluate": ("jaxrender.app.cli.evaluate", "K-fold light cross-validation of the fit against a Lambertian fit"),
}
SIMS_COMMANDS = {
    "ripples": ("jaxrender.app.cli.ripples", "grow wind ripples with the saltation + creep automaton"),
    "dunes": ("jaxrender.app.cli.dunes", "grow dunes with the slope-dependent saltation automaton"),
}


JAXRENDER_DESCRIPTION = "`jaxrender` command line: a thin layer over the public API."
FITTING_DESCRIPTION = ("`fitting` command line: BTF capture synthesis, fitting, pyramid, relighting, reports and "
                       "cross-validation.")
SIMS_DESCRIPTION = "`sims` command line: the Nishimori-Ouchi ripple and dune automata."
COMMAND_TABLES = {  # program: (description, subcommands); docs/_hooks/reference.py writes the CLI pages from it
    "jaxrender": (JAXRENDER_DESCRIPTION, JAXRENDER_COMMANDS),
    "fitting": (FITTING_DESCRIPTION, FITTING_COMMANDS),
    "sims": (SIMS_DESCRIPTION, SIMS_COMMANDS),
}


def jaxrender_main(argv=None) -> int:
    return run_cli("jaxrender", JAXRENDER_DESCRIPTION, JAXRENDER_COMMANDS, argv)


def fitting_main(argv=None) -> int:
    return run_cli("fitting", FITTING_DESCRIPTION, FITTING_COMMANDS, argv)


def sims_main(argv=None) -> int:
    return run_cli("sims", SIMS_DESCRIPTION, SIMS_COMMANDS, argv)


PROGRAMS = {"jaxrender": jaxrender_main, "fitting": fitting_main, "sims": sims_main}

if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in PROGRAMS:
        print(f"usage: python -m {__name__} {{{','.join(PROGRAMS)}}} COMMAND [options]", file=sys.stderr)
        raise SystemExit(2)
    raise SystemExit(PROGRAMS[sys.argv[1]](sys.argv[2:]))
