"""The gallery: the three showcase scenes and a BTF fit, rendered on built-in defaults into
PNG/EXR files and one `index.html` that shows them with their parameters and timings.

Each showcase provides `gallery_section(out_dir, *, quick=False)`, a generator that yields each
entry once its files are written; an entry is {"title", "images" (paths relative to out_dir),
"caption", "params", "timings"}. A section shows its inner progress with `progress_bar`
(`jaxrender.app.gallery.progress`).

With `jobs` > 1 the sections render side by side, each in a process of its own (started afresh:
no state is shared) on its share of the cores (`_core_groups`): much of a first run's time is XLA
compiling the sections' programs, one program at a time on one core, so the other sections
compile or render on the other cores meanwhile (`benchmarks/gallery_time.py`). The longest
sections start first.
"""

from __future__ import annotations

import contextlib
import html
import importlib
import json
import multiprocessing
import multiprocessing.connection
import os
import platform
import time
import traceback
from pathlib import Path

from tqdm import tqdm

from jaxrender.io import atomic_path

from .progress import relay_to

SECTIONS = {
    "stage": ("jaxrender.app.gallery.stage", "Light shafts on a stage (paper 000)"),
    "desert": ("jaxrender.app.gallery.desert", "Desert dunes with wind ripples (paper 001)"),
    "fit": ("jaxrender.app.gallery.fit", "Fitting a BTF to a synthetic multi-light capture (paper 004)"),
    "noh": ("jaxrender.app.gallery.noh", "Woven fabric under dusk sky and firelight (paper 004)"),
}
# the order sections start in when they render side by side: the longest first, so that the last
# one to finish is a short one (full size: the Noh dance takes about as long as the other three)
LONGEST_FIRST = ("noh", "stage", "desert", "fit")


def default_jobs(sections: int) -> int:
    """Sections rendered at once by default: one per core this process may use, at most one per section."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, sections))


def render_gallery(out_dir: str | Path, *, sections: list[str] | None = None, quick: bool = False,
                   log=tqdm.write, jobs: int = 1) -> dict:
    """Render the chosen sections (all by default) into `out_dir`; write `index.html` last.

    `jobs`: sections rendered at once, each in its own process when more than one (module
    docstring); 1 renders them one after the other in this process. Each entry is logged as it is
    written; on a terminal a bar counts the sections (none otherwise). Returns {"sections": {name:
    {"entries": [...], "seconds": float, "error": str | None}}, "quick", "jobs"}, the sections in
    `SECTIONS`' order. A section that fails, or whose process dies, is reported on the page (with
    its traceback or exit code) and in the result; the others still render.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = list(SECTIONS) if sections is None else sections
    unknown = [n for n in names if n not in SECTIONS]
    if unknown:
        raise ValueError(f"unknown gallery sections {unknown}; choose from {list(SECTIONS)}")
    if int(jobs) < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    jobs = min(int(jobs), len(names))
    with tqdm(total=len(names), desc="gallery", unit="section", disable=None) as bar:
        if jobs == 1:
            done = {}
            for name in names:
                done[name] = _render_section(name, SECTIONS[name], out_dir, quick, log)
                bar.update(1)
        else:
            done = _render_side_by_side(names, out_dir, quick, log, jobs, bar.update)
    result = {"sections": {name: done[name] for name in names}, "quick": quick, "jobs": jobs}
    with atomic_path(out_dir / "index.html") as tmp:
        tmp.write_text(_page(result))
    with atomic_path(out_dir / "gallery.json") as tmp:
        tmp.write_text(json.dumps(result, indent=2, default=str))
    return result


def _render_section(name: str, section: tuple[str, str], out_dir: Path, quick: bool, log) -> dict:
    module_name, heading = section
    log(f"[gallery] {name}: {heading} ...")
    start, entries, error = time.perf_counter(), [], None
    try:
        module = importlib.import_module(module_name)
        for entry in module.gallery_section(out_dir / name, quick=quick):
            entry["images"] = [f"{name}/{p}" for p in entry.get("images", [])]  # relative to the section folder
            entries.append(entry)
            log(f"[gallery] {name}: wrote {', '.join(entry['images'])} ({time.perf_counter() - start:.1f} s)")
    except Exception:  # a broken section must not hide the others (nor the entries it already wrote)
        error = traceback.format_exc()
        log(f"[gallery] {name} FAILED:\n{error}")
    seconds = time.perf_counter() - start
    log(f"[gallery] {name}: {len(entries)} entries in {seconds:.1f} s")
    return {"heading": heading, "entries": entries, "seconds": seconds, "error": error}


def _section_process(name: str, section: tuple[str, str], out_dir: Path, quick: bool, messages) -> None:
    """A section in a process of its own: its log lines and bars' steps, then its result, sent on
    `messages` (a pipe's end: each written when sent, so a process that dies has delivered its lines)."""
    relay_to(messages)
    result = _render_section(name, section, out_dir, quick, lambda line: messages.send(("line", line)))
    messages.send(("done", result))


def _core_groups(jobs: int) -> list[set[int] | None]:
    """The cores this process may use, dealt into `jobs` groups, one per section running at once:
    each section's XLA thread pool on its own cores (two processes whose pools each span every
    core slow each other down: in a one-off probe on 2 cores, not a benchmark, the whole gallery
    took longer side by side that way than one section after the other). None each where the
    cores cannot be set."""
    if not hasattr(os, "sched_setaffinity"):
        return [None] * jobs
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < jobs:
        return [None] * jobs
    return [set(cores[k::jobs]) for k in range(jobs)]


@contextlib.contextmanager
def _cores(group: set[int] | None):
    """This process on `group`'s cores meanwhile (a process started meanwhile keeps them)."""
    if group is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, group)
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def _render_side_by_side(names: list[str], out_dir: Path, quick: bool, log, jobs: int, finished) -> dict:
    """Each section in a fresh process, `jobs` at a time, the longest first; their lines passed to
    `log` as they come. {name: section result}."""
    context = multiprocessing.get_context("spawn")   # fresh processes: JAX's runtime does not survive fork
    waiting = sorted(names, key=lambda n: LONGEST_FIRST.index(n) if n in LONGEST_FIRST else len(LONGEST_FIRST))
    running, done, bars = {}, {}, {}   # running: name -> (process, its messages' end, start time, its cores)
    free = _core_groups(jobs)

    def close_bar(name) -> None:
        if name in bars:
            bars.pop(name).close()

    def read(name, connection) -> None:
        while name not in done and connection.poll():
            try:
                kind, value = connection.recv()
            except EOFError:
                return
            if kind == "line":
                log(value)
            elif kind == "bar":
                close_bar(name)
                desc, total, unit = value
                bars[name] = tqdm(total=total, desc=f"{name}: {desc}", unit=unit, leave=False, disable=None)
            elif kind == "advance":
                if name in bars:
                    bars[name].update(value)
            elif kind == "bar_done":
                close_bar(name)
            else:
                done[name] = value

    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                name = waiting.pop(0)
                receive, send = context.Pipe(duplex=False)
                process = context.Process(target=_section_process, name=f"gallery-{name}",
                                          args=(name, SECTIONS[name], out_dir, quick, send))
                group = free.pop(0)
                with _cores(group):   # the process keeps them: XLA sizes its thread pool by them
                    process.start()
                send.close()   # the child's end: this process keeps only the reading one
                running[name] = process, receive, time.perf_counter(), group
            ready = multiprocessing.connection.wait(
                [c for _, c, *_ in running.values()] + [p.sentinel for p, *_ in running.values()])
            for name, (process, connection, start, group) in list(running.items()):
                if connection in ready:
                    read(name, connection)
                if process.sentinel in ready or name in done:
                    process.join()
                    read(name, connection)   # what it sent before it ended
                    if name not in done:     # ended without its result: killed, out of memory
                        error = f"the section's process ended with exit code {process.exitcode} before it finished"
                        log(f"[gallery] {name} FAILED: {error}")
                        done[name] = {"heading": SECTIONS[name][1], "entries": [],
                                      "seconds": time.perf_counter() - start, "error": error}
                    connection.close()
                    close_bar(name)
                    running.pop(name)
                    free.append(group)
                    finished(1)
    finally:
        for name in list(bars):
            close_bar(name)
        for process, connection, *_ in running.values():
            process.terminate()
            process.join()
            connection.close()
    return done


def _table(values: dict) -> str:
    if not values:
        return ""
    rows = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>" for k, v in values.items())
    return f"<table>{rows}</table>"


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _page(result: dict) -> str:
    parts = []
    for name, section in result["sections"].items():
        parts.append(f'<section id="{name}"><h2>{html.escape(section["heading"])}</h2>'
                     f'<p class="meta">section time {section["seconds"]:.1f} s</p>')
        if section["error"]:
            parts.append(f'<pre class="error">{html.escape(section["error"])}</pre>')
        for entry in section["entries"]:
            alt = html.escape(entry.get("title", ""))
            images = "".join(
                f'<a href="{html.escape(p)}"><img src="{html.escape(p)}" alt="{alt}"></a>'
                for p in entry.get("images", []) if p.lower().endswith((".png", ".gif", ".jpg")))
            images += "".join(f'<video src="{html.escape(p)}" controls loop muted></video>'
                              for p in entry.get("images", []) if p.lower().endswith(".mp4"))
            exr = " ".join(f'<a href="{html.escape(p)}">{html.escape(Path(p).name)}</a>'
                           for p in entry.get("images", []) if p.lower().endswith(".exr"))
            parts.append(
                f'<div class="entry"><h3>{html.escape(entry.get("title", ""))}</h3>'
                f'<div class="images">{images}</div>'
                f'<p>{html.escape(entry.get("caption", ""))}</p>'
                + (f'<p class="meta">EXR: {exr}</p>' if exr else "")
                + '<div class="tables"><div><h4>parameters</h4>' + _table(entry.get("params", {}))
                + '</div><div><h4>timings (s)</h4>' + _table(entry.get("timings", {})) + "</div></div></div>")
        parts.append("</section>")
    toc = " · ".join(f'<a href="#{n}">{html.escape(s["heading"])}</a>' for n, s in result["sections"].items())
    machine = f"{platform.platform()}, Python {platform.python_version()}"
    sizes = "quick preview sizes" if result["quick"] else "built-in defaults"
    together = (f" with {result['jobs']} sections rendering at once, each on its share of the cores (its times are "
                "for that share)" if result.get("jobs", 1) > 1 else "")
    meta = (f"{sizes}; {html.escape(machine)}; timings are wall-clock on this machine{together}, "
            "compile time reported apart where given.")
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>jaxrender gallery</title>
<style>
body {{ font-family: sans-serif; margin: 2em; background: #fafafa; color: #222; }}
img, video {{ max-width: 360px; margin: 4px; border: 1px solid #ccc; image-rendering: auto; }}
.entry {{ background: white; padding: 1em; margin: 1em 0; border-radius: 6px; box-shadow: 0 1px 3px #0002; }}
.tables {{ display: flex; gap: 2em; }} table {{ border-collapse: collapse; font-size: 90%; }}
th, td {{ border-bottom: 1px solid #ddd; padding: 2px 8px; text-align: left; }}
.meta {{ color: #666; font-size: 90%; }} .error {{ color: #a00; background: #fee; padding: 1em; overflow-x: auto; }}
</style></head><body>
<h1>jaxrender gallery</h1>
<p class="meta">{meta}</p>
<p>{toc}</p>
{''.join(parts)}
</body></html>
"""
