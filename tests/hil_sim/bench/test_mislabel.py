"""`dct bench mislabel`: the rows over the seeds, and (slow) one episode of each case: the push on
the object the oracle wrongly called movable ends in the correcting mode."""
from __future__ import annotations

import pytest

from hil_sim.bench.mislabel import DEFAULT_CASES, MislabelTask, format_mislabel, mislabel_row, run_mislabel_task


def _record(**kw):
    base = {"scene": "mislabel_cabinet", "seed": 0, "object": "cabinet", "touched": True, "peak_contact_force_n": 200.0,
            "travel_in_contact_m": 0.08, "contact_duration_s": 2.0, "object_moved_m": 0.0, "relabelled_fixed": True,
            "relabelled_by": "push belief", "stuck_s": 3.5, "correcting_s": 3.5, "backed_off_s": 6.9, "corrections": 1,
            "correction_outcomes": ["backed off"], "reached_goal": False, "success": False, "fixed_contacts": 3,
            "failure_reason": "fixed contact: cabinet (3 contact events)", "time_s": 10.0}
    return {**base, **kw}


def test_a_row_counts_the_pushes_and_whether_each_was_corrected():
    rows = [_record(seed=k, peak_contact_force_n=100.0 + 50 * k) for k in range(3)]
    row = mislabel_row("mislabel_cabinet", rows)
    assert row["touched"] == 3 and row["relabelled_fixed"] == 3 and row["all_corrected"]
    assert row["peak_contact_force_n"] == {"p50": 150.0, "max": 200.0} and row["fixed_contacts"] == 9
    assert not mislabel_row("x", rows + [_record(seed=9, relabelled_fixed=False)])["all_corrected"]
    result = {"seeds": 3, "rows": [row], "episodes": rows + [{"scene": "x", "seed": 4, "error": "boom"}],
              "wall_time_s": 1.0, "workers": 1}
    text = "\n".join(format_mislabel(result))
    assert "| mislabel_cabinet | cabinet | 3 | 3 | 150 / 200 |" in text and "error: boom" in text


@pytest.mark.slow
@pytest.mark.parametrize("scene, name", DEFAULT_CASES)
def test_the_push_on_a_mislabelled_object_ends_in_the_correcting_mode(scene, name):
    r = run_mislabel_task(MislabelTask(scene, 0, name))
    assert "error" not in r, r.get("error")
    assert r["touched"] and r["peak_contact_force_n"] > 0.0 and r["object_moved_m"] < 0.05
    assert r["stuck_s"] is not None and r["relabelled_fixed"] and r["backed_off_s"] > r["stuck_s"]
