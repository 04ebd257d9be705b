"""``archer perceive``: the offline contract, and bad grids rejected with exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from onboard.perception import maps
from services.cli.main import main

RES = 0.05
ORIGIN = (1.0, -2.0)


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(["perceive", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def _cells_of(A: np.ndarray, b: np.ndarray, occ: np.ndarray) -> int:
    """Occupied cells whose square overlaps ``A x <= b`` (corner test per face)."""
    rr, cc = np.nonzero(occ)
    x0 = ORIGIN[0] + cc * RES
    y0 = ORIGIN[1] + rr * RES
    lo = A[:, 0][None] * x0[:, None] + A[:, 1][None] * y0[:, None] + RES * (np.minimum(A[:, 0], 0) + np.minimum(A[:, 1], 0))[None]
    return int(np.all(lo < b[None] - 1e-7, axis=1).sum())


@pytest.mark.parametrize("mode", ["free", "obstacles"])
def test_json_contract(tmp_path, capsys, mode):
    tm = maps.rooms(size=120, seed=1)
    grid = tm.occupied.astype(np.uint8) * 100  # nonzero = occupied
    path = tmp_path / "grid.npy"
    np.save(path, grid)
    code, out, err = _run(capsys, "--grid", str(path), "--resolution", str(RES), "--origin", *map(str, ORIGIN), "--mode", mode, "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert doc["mode"] == mode
    assert doc["ms"] > 0
    assert len(doc["polytopes"]) > 0
    rows, cols = grid.shape
    for poly in doc["polytopes"]:
        A, b, V = np.array(poly["A"]), np.array(poly["b"]), np.array(poly["vertices"])
        assert A.shape == (len(b), 2) and V.shape[1] == 2
        assert np.all(A @ V.T <= b[:, None] + 1e-9)  # vertices satisfy the H-form
        # World coordinates: inside the grid's extent.
        assert V[:, 0].min() >= ORIGIN[0] - 1e-9 and V[:, 0].max() <= ORIGIN[0] + cols * RES + 1e-9
        assert V[:, 1].min() >= ORIGIN[1] - 1e-9 and V[:, 1].max() <= ORIGIN[1] + rows * RES + 1e-9
        if mode == "free":
            assert _cells_of(A, b, tm.occupied) == 0
    if mode == "obstacles":
        # A wall cell far from any free space sits inside some obstacle.
        r, c = np.argwhere(tm.occupied)[0]
        p = np.array([ORIGIN[0] + (c + 0.5) * RES, ORIGIN[1] + (r + 0.5) * RES])
        assert any(np.all(np.array(q["A"]) @ p <= np.array(q["b"]) + 1e-9) for q in doc["polytopes"])


def test_rows_are_y_and_origin_is_lower_left(tmp_path, capsys):
    grid = np.zeros((10, 20), dtype=bool)
    grid[7, 3] = True  # row 7 (y), column 3 (x)
    path = tmp_path / "g.npy"
    np.save(path, grid)
    code, out, _ = _run(capsys, "--grid", str(path), "--resolution", "0.5", "--origin", "10", "20", "--mode", "obstacles", "--json")
    assert code == 0
    (poly,) = json.loads(out)["polytopes"]
    V = np.array(poly["vertices"])
    assert np.allclose(V.min(axis=0), [10 + 3 * 0.5, 20 + 7 * 0.5])
    assert np.allclose(V.max(axis=0), [10 + 4 * 0.5, 20 + 8 * 0.5])


@pytest.mark.parametrize(
    "array,message",
    [
        (np.zeros((0, 5)), "empty"),
        (np.zeros((4, 4, 2)), "2D"),
        (np.array([[0.0, np.nan], [0.0, 0.0]]), "NaN"),
        (np.array([["a", "b"], ["c", "d"]]), "dtype"),
        (np.zeros((3, 3), dtype=complex), "dtype"),
        (np.zeros(7), "2D"),
    ],
)
def test_bad_grids_exit_2_with_a_clear_error(tmp_path, capsys, array, message):
    path = tmp_path / "bad.npy"
    np.save(path, array)
    code, out, err = _run(capsys, "--grid", str(path), "--resolution", "0.05", "--origin", "0", "0", "--json")
    assert code == 2
    assert out == ""
    assert message in err


def test_bad_files_and_arguments_exit_2(tmp_path, capsys):
    code, _, err = _run(capsys, "--grid", str(tmp_path / "missing.npy"), "--resolution", "0.05", "--origin", "0", "0")
    assert code == 2 and "not found" in err
    junk = tmp_path / "junk.npy"
    junk.write_bytes(b"not numpy at all")
    code, _, err = _run(capsys, "--grid", str(junk), "--resolution", "0.05", "--origin", "0", "0")
    assert code == 2 and "npy" in err
    obj = tmp_path / "obj.npy"
    np.save(obj, np.array([[None, 1]], dtype=object), allow_pickle=True)
    code, _, err = _run(capsys, "--grid", str(obj), "--resolution", "0.05", "--origin", "0", "0")
    assert code == 2
    good = tmp_path / "good.npy"
    np.save(good, np.zeros((5, 5)))
    for res in ("0", "-1", "nan"):
        code, _, err = _run(capsys, "--grid", str(good), "--resolution", res, "--origin", "0", "0")
        assert code == 2 and "resolution" in err
    code, _, err = _run(capsys, "--grid", str(good), "--resolution", "0.1", "--origin", "inf", "0")
    assert code == 2 and "origin" in err


def test_entry_point_runs_as_a_process(tmp_path):
    path = tmp_path / "grid.npy"
    np.save(path, maps.clutter(size=80, seed=3).occupied)
    done = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "perceive", "--grid", str(path), "--resolution", "0.05", "--origin", "0", "0", "--json"],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1])["mode"] == "free"
    bad = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "perceive", "--grid", str(tmp_path / "nope.npy"), "--resolution", "0.05", "--origin", "0", "0"],
        capture_output=True, text=True, timeout=120,
    )
    assert bad.returncode == 2 and "archer perceive:" in bad.stderr
