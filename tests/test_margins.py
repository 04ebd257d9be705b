"""archer margins' analysis (offline/margins.py): a rung fails on any fall, misses on a missed goal,
"holds to" stops at the first rung that is not clean, and the table and plot are written."""

from __future__ import annotations

import json

from offline import margins as mg


def _record(factor: str, value: float, config: str, seed: int, falls: int = 0, reached: bool = True,
            error: float = 0.004, crashed: bool = False) -> dict:
    options = {"estimator": "kalman", "model-error": mg.rung_error(factor, value)}
    if config:
        options["config"] = config
    rec: dict = {"spec": {"scenario": "hop-in-place", "seed": seed, "variant": "indoor", "options": options}}
    if crashed:
        rec["error"] = "WorkerCrash: killed"
    else:
        rec["report"] = {"falls": falls, "goal_reached": reached and not falls, "collisions": 0, "final_goal_error_m": error}
    return rec


def test_margins_find_the_first_miss_and_the_first_fall_per_config(tmp_path) -> None:
    lad = mg.ladder("com_x")
    before, after = "before.toml", "after.toml"
    records = []
    for i, value in enumerate(lad.values):
        for seed in (0, 1):
            # before: misses from the first rung, falls from the fourth; after: clean to the third, one seed falls at the fourth
            records.append(_record("com_x", value, before, seed, falls=int(i >= 3), reached=False, error=0.14))
            records.append(_record("com_x", value, after, seed, falls=int(i >= 3 and seed == 1), reached=i < 3 or seed == 1))
    records.append(_record("com_x", lad.values[4], after, 2, crashed=True))
    specs = mg.specs([lad], ["hop-in-place"], [0, 1], [before, after], "indoor")
    assert len(specs) == 2 * len(lad.values) * 2
    assert {s["options"]["model-error"] for s in specs} == {f"com_x={v:g}" for v in lad.values}

    results = {m.config: m for m in mg.margins(records, [lad], [before, after])}
    b, a = results[before], results[after]
    assert (b.holds_to, b.first_miss, b.first_fall) == (None, lad.values[0], lad.values[3])
    assert (a.holds_to, a.first_miss, a.first_fall) == (lad.values[2], lad.values[3], lad.values[3])
    assert a.rungs[4].errors == 1 and a.rungs[4].verdict == "fall"  # a crash is counted apart, never a margin
    assert b.rungs[1].goal_error_max == 0.14 and b.rungs[3].verdict == "fall"

    md, png = mg.write(list(results.values()), [before, after], tmp_path)
    text = md.read_text()
    assert "| `com_x` |" in text and "- / 0.01 / 0.04" in text and "0.03 / 0.04 / 0.04 (1 runs crashed)" in text
    assert png.stat().st_size > 10_000
    rungs = json.loads((tmp_path / "margins.json").read_text())
    assert [r["config"] for r in rungs] == ["before", "after"]


def test_a_factor_without_a_ladder_is_refused() -> None:
    try:
        mg.ladder("mass_torso")
    except ValueError as exc:
        assert "no ladder for 'mass_torso'" in str(exc)
    else:
        raise AssertionError("mass_torso has no ladder")
