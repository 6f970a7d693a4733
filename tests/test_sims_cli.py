"""`sims ripples` / `sims dunes`: outputs equal the API's, --init continues a run, bad input is
one line on stderr with exit code 2 and no output file."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.app.cli.programs import sims_main as main
from jaxrender.io import read_exr, read_image
from sims import DuneParams, RippleParams, init_dunes, init_ripples, simulate_dunes, simulate_ripples

_F32_TOL = 1e-5  # float32 output file vs the float64 API run: rounding of ~10-unit heights


def test_ripples_cli_matches_api_and_continues(tmp_path, capsys):
    out = tmp_path / "r.npy"
    rc = main(["ripples", "--size", "12x16", "--steps", "130", "--L0", "3.1", "--q", "0.5", "--b", "1.5",
               "--D", "0.7", "--wind-deg", "20", "--seed", "3", "--out", str(out),
               "--preview", str(tmp_path / "r.png")])
    assert rc == 0
    params = RippleParams(L0=3.1, q=0.5, b=1.5, D=0.7, wind_deg=20.0)
    api = simulate_ripples(init_ripples(jax.random.key(3), (12, 16)), params, steps=130)
    field = np.load(out)
    assert field.shape == (12, 16) and field.dtype == np.float32
    np.testing.assert_allclose(field, np.asarray(api), atol=_F32_TOL)
    preview = read_image(tmp_path / "r.png", srgb=False)
    assert preview.shape[:2] == (12, 16) and preview.max() > preview.min()
    # continue from the written field, to EXR
    out2 = tmp_path / "r2.exr"
    assert main(["ripples", "--init", str(out), "--steps", "7", "--L0", "3.1", "--q", "0.5", "--b", "1.5",
                 "--D", "0.7", "--wind-deg", "20", "--out", str(out2)]) == 0
    cont = simulate_ripples(jnp.asarray(field), params, steps=7)
    np.testing.assert_allclose(read_exr(out2)["height"], np.asarray(cont), atol=_F32_TOL)
    assert "wrote" in capsys.readouterr().out


def test_dunes_cli_matches_api(tmp_path):
    out = tmp_path / "d.npy"
    assert main(["dunes", "--size", "10", "--steps", "40", "--q0", "1.2", "--b-prime", "1.5", "--hop", "nearest",
                 "--seed", "1", "--out", str(out)]) == 0
    api = simulate_dunes(init_dunes(jax.random.key(1), (10, 10)), DuneParams(q0=1.2, b_prime=1.5, hop="nearest"),
                         steps=40)
    np.testing.assert_allclose(np.load(out), np.asarray(api), atol=_F32_TOL)


def _bad_inputs(tmp_path):
    garbage = tmp_path / "garbage.npy"
    garbage.write_bytes(b"not a numpy file")
    cube = tmp_path / "cube.npy"
    np.save(cube, np.zeros((3, 4, 5)))
    nan = tmp_path / "nan.npy"
    np.save(nan, np.full((5, 5), np.nan))
    return [
        (["ripples", "--init", str(garbage)], "garbage.npy"),
        (["ripples", "--init", str(cube)], "2-D"),
        (["dunes", "--init", str(nan)], "NaN"),
        (["dunes", "--init", str(tmp_path / "missing.npy")], "no such file"),
        (["ripples", "--init", str(tmp_path / "f.txt")], ".npy or .exr"),
        (["ripples", "--size", "8x"], "--size"),
        (["dunes", "--size", "2"], "at least 3x3"),
        (["ripples", "--steps", "-1"], "--steps"),
        (["ripples", "--D", "1.5"], "--D"),
        (["ripples", "--L0", "nan"], "finite"),
    ]


def test_bad_input_one_line_exit_2(tmp_path, capsys):
    for argv, needle in _bad_inputs(tmp_path):
        out = tmp_path / "out.npy"
        rc = main(argv + ["--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2, argv
        assert err.count("\n") == 1 and needle in err and "Traceback" not in err, (argv, err)
        assert not out.exists()
    rc = main(["ripples", "--out", str(tmp_path / "field.txt")])
    assert rc == 2 and "field.txt" in capsys.readouterr().err
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temporaries left


@pytest.mark.parametrize("argv", [["ripples", "--hop", "bogus"], ["dunes", "--steps", "many"],
                                  ["ripples", "--b", "1e39"]])
def test_argparse_errors_exit_2(argv, tmp_path, capsys):
    assert main(argv + ["--out", str(tmp_path / "x.npy")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sims ") and "usage" not in err, err
