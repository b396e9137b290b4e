"""The benchmarks' scripts run: benchmarks/pipeline.py's whole chain on a tiny made-up set (its own file, so that the
test workers share the suite's load evenly)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path


def test_the_whole_chain_benchmark_runs_a_tiny_set_and_prints_every_stage_with_progress_lines(tmp_path):
    """benchmarks/pipeline.py --tiny: the real pipeline (every stage its own process) on a made-up set; its table
    lists every stage with a wall time and share, then the end scores; the pipeline's progress lines (every 0.5 s here)
    say what the running stage does and when the whole run should end. Numbers are not asserted."""
    script = Path(__file__).parent.parent / "benchmarks" / "pipeline.py"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(script), "--tiny", "--out", str(tmp_path / "run"), "--progress", "0.5"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    table = done.stdout.split("## drgan.pipeline on a tiny made-up set")[1]
    for stage in ("profile", "train", "generate", "segment", "analyze", "evaluate"):
        assert re.search(rf"^\| {stage} \| done \| \d+ \| [\d.]+ \| \d+% \| ", table, re.M), (stage, table)
    assert re.search(r"^\| \*\*total\*\* \| \| \*\*\d+\*\* \|", table, re.M)
    assert re.search(r"^\| test DSC \| \d\.\d{3} \|$", table, re.M), table
    ticks = re.findall(r"^\[(\d)/6\] (\w+): (.*); the whole run: ~[\d.]+ (?:s|min) left, ends ~\d\d:\d\d \(estimate\)$",
                       done.stdout, re.M)  # fmt: skip
    assert {stage for _, stage, _ in ticks} >= {"train", "segment"}, done.stdout[-3000:]
    # the stages' own reports reach the line: the training steps of the GAN and of the segmenter
    assert any(
        stage == "train" and re.match(r"training the GAN .* [0-9]+/[0-9]+ steps", doing) for _, stage, doing in ticks
    )
