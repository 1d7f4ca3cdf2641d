"""benches/arch_cost.py on a tiny region: one line per shape, costs that follow the shape."""

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_arch_cost_reports_each_shape(capsys):
    sys.path.insert(0, str(ROOT / "benches"))
    import arch_cost

    assert arch_cost.main(["--size", "40x24", "--runs", "1", "--threads", "1",
                           "--shape", "{}", "--shape", '{"dec": [16, 32, 48, 64]}']) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["name"] for r in rows] == ["shape0", "shape1"]
    shipped, cheaper = rows
    assert shipped["shape"]["dec"] == [32, 32, 48, 64] and cheaper["shape"]["dec"] == [16, 32, 48, 64]
    assert shipped["size"] == "48x32"  # padded to the 5-level network's multiple of 16
    assert cheaper["mflop_per_px"] < shipped["mflop_per_px"] and cheaper["params"] < shipped["params"]
    assert shipped["mflop_per_px"] == 0.137 and all(r["seconds"] > 0 for r in rows)
