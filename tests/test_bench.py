"""laserrl-bench prints one table row per solver with rates, ratios and accuracy."""
import re
import statistics

import pytest
import torch

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


def test_loop_rates_count_frames_and_learning_time_after_the_warmup():
    from laserrl.bench_train import loop_rates

    history = [{"frames": 0, "time_s": 0.0, "eval/success_rate": 0.0}]  # rows without learn time are skipped
    history += [{"frames": 64 * i, "time_s": 2.0 * i, "time/learn_s": 0.5, "train/round_trips_per_step": 10.0 + i}
                for i in range(1, 6)]
    rates = loop_rates(history, warmup_frames=128)  # counted from the row at 128 frames (t = 4 s) to 320 (t = 10 s)
    assert rates["frames"] == 192 and rates["seconds"] == pytest.approx(6.0)
    assert rates["frames_per_s"] == pytest.approx(32.0)
    assert rates["learn_share"] == pytest.approx(1.5 / 6.0) and rates["sim_share"] == pytest.approx(0.75)
    assert rates["round_trips_per_step"] == pytest.approx(14.0)  # rows at 192, 256, 320 frames
    with pytest.raises(ValueError, match="raise --train-frames"):
        loop_rates(history, warmup_frames=320)


def test_bench_train_loop_times_real_training_runs(capsys):
    assert main(["--train-loop", "--train-frames", "128", "--train-warmup-frames", "32",
                 "--train-override", "experiment=smoke", "--train-override", "env.num_envs=8"]) == 0
    out = capsys.readouterr().out
    assert "training loop: 128 frames per run (stage=miso, stage.K=0.1, experiment=smoke" in out
    rows = [line for line in out.splitlines() if line.startswith("| 1 process")]
    assert len(rows) == 2
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        fps, sim, learn = float(cells[1].replace(",", "")), float(cells[3].rstrip("%")), float(cells[4].rstrip("%"))
        assert fps > 0 and 0 <= sim <= 100 and 0 <= learn <= 100 and sim + learn == pytest.approx(100, abs=1)
    assert rows[0].split("|")[3].strip() == "1.00"  # the ratios are against threads=null
    assert torch.get_num_threads() == 1  # the benchmark gives the process its thread count back (conftest: 1)


def test_bench_train_loop_refuses_a_budget_inside_the_warmup():
    with pytest.raises(SystemExit):
        main(["--train-loop", "--train-frames", "64", "--train-warmup-frames", "64"])
