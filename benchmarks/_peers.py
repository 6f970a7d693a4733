"""Benchmark peers in a child process: a peer that dies (Mitsuba's LLVM backend aborts with SIGABRT
inside an old system LLVM on AVX-512 CPUs) is recorded as unavailable with its reason, and the
benchmark's own figures still count.

    with ChildPeer("Mitsuba 3") as peer:
        image, seconds = peer.call(render_fn, scene_dict, spp, seed)   # PeerUnavailable if it dies

`mitsuba_variant()` probes Mitsuba's variants each in its own child (`llvm_ad_rgb` with the newest
LLVM found, else `scalar_rgb`) and returns the first that renders, with a note naming what failed.
The functions a child runs must be importable (module level; a script's own functions need its
`if __name__ == "__main__":` guard, as `multiprocessing`'s spawn re-imports it).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import tempfile
from pathlib import Path

__all__ = ["ChildPeer", "PeerUnavailable", "mitsuba_variant", "LLVM_CANDIDATES"]

# Dr.Jit 1.5 needs an LLVM newer than Debian 12's default 14/15 on AVX-512 CPUs
# (benchmarks/system_packages.sh installs libllvm19); the first that exists is used
LLVM_CANDIDATES = [
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-18.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-17.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-16.so",
]


class PeerUnavailable(RuntimeError):
    """The peer died or failed; `reason` says how, in one line."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(reason)


def _serve(conn, stderr_path: str) -> None:
    """The child: stderr into a file (an aborting library dumps pages there), then run calls until None."""
    fd = os.open(stderr_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.dup2(fd, 2)
    while True:
        message = conn.recv()
        if message is None:
            return
        fn, args, kwargs = message
        try:
            conn.send(("ok", fn(*args, **kwargs)))
        except BaseException as error:  # noqa: BLE001 - any failure of the peer is reported, not raised here
            conn.send(("error", f"{type(error).__name__}: {error}"))


def _death_reason(name: str, exitcode: int | None, stderr_path: Path) -> str:
    how = (f"killed by {signal.Signals(-exitcode).name}" if exitcode is not None and exitcode < 0
           else f"exited with code {exitcode}")
    lines = [ln.strip() for ln in stderr_path.read_text(errors="replace").splitlines() if ln.strip()]
    # LLVM's abort ends a long dump; its first line says what failed ("LLVM ERROR: Cannot select: ...")
    key = next((ln for ln in lines if "LLVM ERROR" in ln or "Error" in ln), lines[-1] if lines else "")
    return f"{name} {how}" + (f" ({key[:200]})" if key else "")


class ChildPeer:
    """One spawned child process that runs a peer's calls in turn (its JIT caches persist between
    calls); a call raises `PeerUnavailable` when the peer raises or the child dies, and a dead
    child stays dead (every later call raises the same reason)."""

    def __init__(self, name: str, *, timeout_s: float | None = None):
        self.name, self.timeout_s = name, timeout_s
        self.dead: str | None = None
        self._process = None

    def __enter__(self) -> "ChildPeer":
        context = multiprocessing.get_context("spawn")
        self._stderr = Path(tempfile.mkstemp(prefix="peer-", suffix=".stderr")[1])
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, str(self._stderr)), daemon=True)
        self._process.start()
        child.close()
        return self

    def __exit__(self, *exc) -> None:
        if self._process is not None and self._process.is_alive():
            try:
                self._conn.send(None)
            except OSError:
                pass
            self._process.join(10)
            if self._process.is_alive():
                self._process.kill()
        self._stderr.unlink(missing_ok=True)

    def call(self, fn, *args, **kwargs):
        if self.dead:
            raise PeerUnavailable(self.dead)
        try:
            self._conn.send((fn, args, kwargs))
            waited = 0.0
            while not self._conn.poll(1.0):
                waited += 1.0
                if not self._process.is_alive():
                    raise EOFError
                if self.timeout_s is not None and waited > self.timeout_s:
                    self._process.kill()
                    self.dead = f"{self.name} did not answer within {self.timeout_s:.0f} s"
                    raise PeerUnavailable(self.dead)
            status, value = self._conn.recv()
        except (EOFError, OSError, BrokenPipeError):
            self._process.join(5)
            self.dead = _death_reason(self.name, self._process.exitcode, self._stderr)
            raise PeerUnavailable(self.dead) from None
        if status != "ok":
            raise PeerUnavailable(f"{self.name} failed: {value}")
        return value


def _render_probe(variant: str) -> str:
    """A small volumetric render (spot light, homogeneous fog, volpath): the kernels the benchmarks JIT."""
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "volpath", "max_depth": 2},
        "fog": {"type": "homogeneous", "sigma_t": 0.2, "albedo": 0.5},
        "sensor": {"type": "perspective", "fov": 40, "medium": {"type": "ref", "id": "fog"},
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1, 5], target=[0, 1, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 12, "rfilter": {"type": "box"}}},
        "light": {"type": "spot", "cutoff_angle": 20, "intensity": 40, "medium": {"type": "ref", "id": "fog"},
                  "to_world": mi.ScalarTransform4f().look_at(origin=[0, 4, 0], target=[0, 0, 0], up=[0, 0, 1])},
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}, "exterior": {"type": "ref", "id": "fog"},
                  "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3)},
    })
    image = np.array(mi.render(scene, spp=4))
    if not np.isfinite(image).all():
        raise RuntimeError("non-finite pixels")
    return mi.__version__


def mitsuba_variant(preferred: tuple[str, ...] = ("llvm_ad_rgb", "scalar_rgb")) -> tuple[str | None, str]:
    """(the first of `preferred` whose probe renders in a child process, or None; a note for the report).

    Sets DRJIT_LIBLLVM_PATH to the newest LLVM of `LLVM_CANDIDATES` when it is unset (the children
    inherit it)."""
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        found = next((p for p in LLVM_CANDIDATES if os.path.exists(p)), None)
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found
    failures = []
    for variant in preferred:
        with ChildPeer(f"Mitsuba {variant}", timeout_s=600) as peer:
            try:
                version = peer.call(_render_probe, variant)
            except PeerUnavailable as error:
                failures.append(error.reason)
                continue
        llvm = f" with {os.environ.get('DRJIT_LIBLLVM_PATH', 'the default LLVM')}" if "llvm" in variant else ""
        note = f"Mitsuba {version} {variant}{llvm}"
        return variant, note + (f" (FALLBACK: {'; '.join(failures)})" if failures else "")
    return None, "Mitsuba unavailable: " + "; ".join(failures)
