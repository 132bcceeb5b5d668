"""laserrl-bench prints one table row per solver with rates, ratios and accuracy."""
import re
import statistics

import pytest

from laserrl.bench import main


def test_bench_prints_table_with_ratio_and_accuracy(capsys):
    assert main(["--batch-sizes", "1", "4", "--scipy-round-trips", "2", "--min-seconds", "0.05", "--no-compile",
                 "--threads", "1"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| torch batch")]
    assert [r.split("|")[2].strip() for r in rows] == ["1", "4"]
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        rate, ratio, bound, err = (float(cells[i].replace(",", "")) for i in (2, 3, 4, 5))
        assert rate > 0 and ratio > 0 and bound > 0
        assert err <= 1e-4  # default-settings accuracy against the stored reference
    paper = next(line for line in out.splitlines() if line.startswith("| scipy DOP853 (paper's code, rtol 1e-6), 1 cavity"))
    loose = next(line for line in out.splitlines() if line.startswith("| scipy DOP853 (rtol 1e-3), 1 cavity"))
    assert float(paper.split("|")[6]) < 1e-7  # the paper's tolerance: far tighter than the torch solver's 1e-4
    assert float(paper.split("|")[6]) < float(loose.split("|")[6]) < 1e-4
    assert float(paper.split("|")[4]) == 1  # the ratios are against the paper's reference
    # the reference is timed before, between and after torch, and the median of the three is used
    times = re.search(r"reference timed 3 times .*?: ([\d.]+), ([\d.]+), ([\d.]+) ms per round trip", out)
    assert times
    median_ms = statistics.median(float(t) for t in times.groups())
    assert float(paper.split("|")[3].replace(",", "")) == pytest.approx(1e3 / median_ms, rel=0.02, abs=1)
    assert re.search(r"best: [\d,]+ cavity round trips/s at batch \d+ = [\d,]+x the scipy reference", out)


def test_bench_times_the_whole_machine_with_simultaneous_processes(capsys):
    assert main(["--batch-sizes", "2", "--scipy-round-trips", "2", "--min-seconds", "0.2", "--no-compile",
                 "--threads", "1", "--skip-accuracy", "--processes", "2", "--process-batch", "3"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| torch 2 processes x batch 3"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    rate, ratio = float(cells[2].replace(",", "")), float(cells[3].replace(",", ""))
    scipy_1 = float(next(line for line in out.splitlines() if line.startswith("| scipy DOP853 (paper's code, rtol 1e-6), 1 cavity"))
                    .split("|")[3].replace(",", ""))
    assert rate > 0 and abs(ratio - rate / scipy_1) <= 0.5 + 0.01 * ratio  # the ratio is against one scipy process
    assert next(line for line in out.splitlines() if line.startswith("| scipy DOP853 (paper's code, rtol 1e-6), 2 processes"))
    assert re.search(r"whole machine: [\d,]+ cavity round trips/s with 2 processes = [\d,]+x the one-process scipy "
                     r"reference, [\d,]+x scipy on 2 processes", out)


def test_a_failing_benchmark_process_raises_instead_of_hanging():
    from laserrl.bench import time_processes
    from laserrl.physics import CavityParams

    with pytest.raises(RuntimeError, match="a torch benchmark process failed"):
        time_processes("torch", 2, 2, CavityParams(), "no-such-device", False, 0.1)


def test_bench_refuses_a_non_positive_process_count():
    with pytest.raises(SystemExit):
        main(["--processes", "0"])
