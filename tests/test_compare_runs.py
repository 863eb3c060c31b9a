"""benchmarks/compare_runs.py: reading run metrics and tabulating them at given minutes."""

import importlib.util
import pathlib

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location("compare_runs", pathlib.Path(__file__).parents[1] / "benchmarks" / "compare_runs.py")
compare_runs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare_runs)


def _run(tmp_path, rows):
    header = "iteration,env_steps,seconds,level,window_success,level_1,level_2,window_success_1,window_success_2"
    (tmp_path / "metrics.csv").write_text(header + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return compare_runs.read_metrics(tmp_path)


def test_at_minute_levels_steps_and_windowed_success(tmp_path):
    # one row per minute: 1-arm level climbs, 2-arm success alternates 0 / 1
    metrics = _run(tmp_path, [(i, 1000 * i, 60.0 * i, 0, 0.5, i, i // 2, 1.0, i % 2) for i in range(1, 11)])
    assert compare_runs.team_sizes(metrics) == [1, 2]
    point = compare_runs.at_minute(metrics, 6.5, window=4.0)
    assert point["env_steps"] == 6000  # the last row at or before 6.5 min
    assert point["level"] == {1: 7, 2: 4}  # 1-based
    assert point["success"][1] == 1.0
    assert point["success"][2] == pytest.approx(np.mean([1, 0, 1, 0]))  # minutes 3..6
    assert compare_runs.at_minute(metrics, 10.5, window=4.0) is None  # past the run's end
    assert compare_runs.at_minute(metrics, 0.5, window=4.0) is None  # before the first row


def test_trailing_mean_and_missing_run(tmp_path):
    np.testing.assert_allclose(compare_runs.trailing_mean(np.array([2.0, 4.0, 6.0, 8.0]), 2), [2, 3, 5, 7])
    with pytest.raises(FileNotFoundError, match="no metrics"):
        compare_runs.read_metrics(tmp_path / "nowhere")
