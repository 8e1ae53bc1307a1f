"""scripts/stress.py end to end on its smallest configuration (``--tiny``: one well-conditioned pair combination,
15 hypothesis examples, one mesh scale, three steps per scene). The pair, mesh and step sections must find no
failure there; the fuzzing section only has to run (its random near-margin pairs hit the known accuracy limits
reported by the full sweep). The sweep itself (``make stress``) is not part of the test suite."""

from __future__ import annotations

import json
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


def test_stress_script_tiny_configuration(tmp_path):
    sys.path.insert(0, str(SCRIPTS))
    try:
        import stress
    finally:
        sys.path.remove(str(SCRIPTS))
    stress.main(["--tiny", "--out", str(tmp_path)])
    out = json.loads((tmp_path / "stress.json").read_text())
    cases = out["cases"]
    assert {c["section"] for c in cases} == {"pair", "fuzz", "mesh", "step"}
    assert sum(c["section"] == "fuzz" for c in cases) == 15
    fails = [c for c in cases if c["section"] != "fuzz" and c["outcome"] not in ("ok", "rejected")]
    assert not fails, fails[:3]
    assert (tmp_path / "stress.md").read_text().startswith("Numerical-robustness sweep")
