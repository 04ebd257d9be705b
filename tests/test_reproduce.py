"""``archer reproduce``: the report is produced from real runs, resumes without rerunning, refuses
bad requests; verdicts come from the rows; the impact angle is measured as the figure draws it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from services.reproduce.engine import _quat_tilt
from services.reproduce.catalogue import load_all
from services.reproduce.items import DIFFERS, MEASURED, PARTLY, REPRODUCED, ItemResult, Row, thesis_line

REPO = Path(__file__).resolve().parent.parent


def archer(*argv: str, timeout: float = 600.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli.main", "reproduce", *argv], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout)


def test_a_quick_reproduction_writes_the_report_and_resumes_without_running_again(tmp_path: Path) -> None:
    out = tmp_path / "repro"
    proc = archer("--quick", "--only", "fig6.2,hops3000", "--out", str(out), "--workers", "1", "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(summary["items"]) == {"fig6.2", "hops3000"} and not summary["failed"]
    report = (out / "report.md").read_text()
    for name in ("fig6.2", "hops3000"):
        assert f"## {name}" in report
        assert summary["items"][name] in (REPRODUCED, DIFFERS, PARTLY)
    assert (out / "fig6_2.png").stat().st_size > 10_000  # a drawn figure, linked from the report
    assert "![fig6.2](fig6_2.png)" in report
    hops = json.loads((out / "items" / "hops3000.json").read_text())
    assert "hops in" in hops["rows"][0]["ours"] and hops["runs"] == 1
    run_lines = (out / "runs" / "hops3000.jsonl").read_text().splitlines()
    assert len(run_lines) == 1 and json.loads(run_lines[0])["report"]["sim_time_s"] == pytest.approx(60.0, abs=0.01)

    published = tmp_path / "docs" / "reproduction.md"
    again = archer("--quick", "--only", "fig6.2,hops3000", "--out", str(out), "--workers", "1", "--quiet", "--report", str(published))
    assert again.returncode == 0, again.stderr[-3000:]
    assert "![fig6.2](reproduction/fig6_2.png)" in published.read_text()  # the figures beside it, linked there
    assert (tmp_path / "docs" / "reproduction" / "fig6_2.png").read_bytes() == (out / "fig6_2.png").read_bytes()
    assert (out / "runs" / "hops3000.jsonl").read_text().splitlines() == run_lines  # nothing ran again
    assert json.loads(again.stdout.strip().splitlines()[-1])["items"] == summary["items"]

    # --redo runs the item's lockstep runs again: none of the kept ones (another commit's) is reported
    stale = json.loads(run_lines[0])
    stale["report"]["hops"] = -1
    (out / "runs" / "hops3000.jsonl").write_text(json.dumps(stale) + "\n")
    redo = archer("--quick", "--only", "hops3000", "--out", str(out), "--workers", "1", "--quiet", "--redo")
    assert redo.returncode == 0, redo.stderr[-3000:]
    redone = (out / "runs" / "hops3000.jsonl").read_text().splitlines()
    assert len(redone) == 1 and json.loads(redone[0])["report"]["hops"] > 0


def test_bad_requests_are_refused(tmp_path: Path) -> None:
    proc = archer("--only", "fig9.99", "--out", str(tmp_path / "a"))
    assert proc.returncode == 2 and "unknown items" in proc.stderr
    quick = tmp_path / "b"
    assert archer("--quick", "--only", "fig6.2", "--out", str(quick), "--quiet").returncode == 0
    mixed = archer("--only", "fig6.2", "--out", str(quick))
    assert mixed.returncode == 2 and "holds a quick reproduction" in mixed.stderr


def test_an_item_is_reproduced_only_when_every_row_is() -> None:
    ok, bad = Row("a", "t", "o", REPRODUCED), Row("b", "t", "o", DIFFERS)
    assert ItemResult([ok, ok]).verdict == REPRODUCED
    assert ItemResult([ok, bad]).verdict == PARTLY
    assert ItemResult([bad]).verdict == DIFFERS
    info = Row("c", "no number given", "o", MEASURED)  # reported, never judged
    assert ItemResult([ok, info]).verdict == REPRODUCED and ItemResult([bad, info]).verdict == DIFFERS
    back = ItemResult.from_json(json.loads(json.dumps(ItemResult([ok, bad], ["f.png"], ["n"], 3, 1.5).to_json())))
    assert back.rows == [ok, bad] and back.figures == ["f.png"] and back.runs == 3


def test_every_item_cites_a_thesis_line_and_they_are_listed_in_its_order() -> None:
    items = list(load_all().values())
    lines = [thesis_line(i.where) for i in items]
    assert lines == sorted(lines) and len(items) >= 14
    assert any(i.quick for i in items) and not all(i.quick for i in items)
    with pytest.raises(ValueError, match="must cite a line"):
        thesis_line("Fig. 5.12")


def test_the_impact_angle_is_the_body_axis_lean_toward_x_and_y() -> None:
    theta = 0.2
    about_y = (math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0)  # leans the body z axis toward +x
    about_x = (math.cos(theta / 2), math.sin(theta / 2), 0.0, 0.0)  # toward -y
    assert _quat_tilt(about_y) == pytest.approx((theta, 0.0), abs=1e-12)
    assert _quat_tilt(about_x) == pytest.approx((0.0, -theta), abs=1e-12)
    assert _quat_tilt((1.0, 0.0, 0.0, 0.0)) == (0.0, 0.0)
