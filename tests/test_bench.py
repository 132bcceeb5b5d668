"""laserrl-bench prints one table row per solver with rates, ratios and accuracy."""
import re

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
    scipy_row = next(line for line in out.splitlines() if line.startswith("| scipy"))
    assert float(scipy_row.split("|")[6]) < 1e-4
    assert re.search(r"best: [\d,]+ cavity round trips/s at batch \d+ = [\d,]+x the scipy reference", out)
