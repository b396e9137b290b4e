"""drgan.core.progress: the estimate of the time left, the console lines off a terminal, the progress file."""

from __future__ import annotations

import json

import pytest

from drgan.core import progress


def test_the_estimate_is_the_rate_so_far_without_the_first_units_start_up():
    # 4 of 10 done in 40 s: 10 s each, 60 s left
    assert progress.estimate_left(4, 10, 40.0) == pytest.approx(60.0)
    # the first unit took 25 s (start-up), the next three 5 s each: 6 more at 5 s
    assert progress.estimate_left(4, 10, 40.0, first_unit_s=25.0) == pytest.approx(30.0)
    assert progress.estimate_left(0, 10, 5.0) is None  # nothing done: no rate yet
    assert progress.estimate_left(3, None, 5.0) is None  # no total: no estimate
    assert progress.estimate_left(10, 10, 5.0) == 0.0


def test_off_a_terminal_a_task_prints_lines_and_writes_its_progress_file(tmp_path, monkeypatch, capsys):
    file = tmp_path / "stage" / "progress.json"
    monkeypatch.setenv(progress.FILE_ENV, str(file))
    monkeypatch.setenv(progress.EVERY_ENV, "1e-9")  # a line at every update
    monkeypatch.setenv(progress.STAGE_ENV, "generate")
    monkeypatch.setattr(progress, "FILE_INTERVAL_S", 0.0)
    with progress.Task("rendering pairs", 10, "pairs", start=4) as task:  # a resumed job: 4 done before
        task.advance()
        assert json.loads(file.read_text())["done"] == 5
        report = progress.read_report(file)
        assert (report.task, report.total, report.stage, report.finished) == ("rendering pairs", 10, "generate", False)
        task.advance()
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("progress: generate: rendering pairs 5/10 pairs (50 %), 0 s so far, ~")
    assert lines[-1].startswith("progress: generate: rendering pairs 6/10 pairs (60 %)") and lines[-1].endswith("done")
    assert progress.read_report(file).finished is True


def test_track_reports_each_item_and_reads_the_total_from_the_items(tmp_path, monkeypatch):
    file = tmp_path / "progress.json"
    monkeypatch.setenv(progress.FILE_ENV, str(file))
    monkeypatch.setattr(progress, "FILE_INTERVAL_S", 0.0)
    seen = []
    for item in progress.track(["a", "b", "c"], "reading", unit="images"):
        seen.append((item, progress.read_report(file)))
    assert [item for item, _ in seen] == ["a", "b", "c"]
    assert seen[1][1].done == 1 and seen[1][1].total == 3  # the report after the first item
    assert progress.read_report(file).done == 3 and progress.read_report(file).finished


@pytest.mark.parametrize("seconds, text", [(45, "45 s"), (378, "6.3 min"), (5040, "84.0 min"), (7200, "2.0 h")])
def test_durations_read_as_a_person_says_them(seconds, text):
    assert progress.duration(seconds) == text
