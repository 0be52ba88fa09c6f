"""A small map job for the daemon tests: two placements of the thesis four-ball artefact, nine
indexations each, on the simulator whose errors carry the 18 motion errors."""

from __future__ import annotations

import yaml

from benchmarks.rigs.daemon_helpers import CONFIG
from simulators.truth import TruthModel

MACHINE = CONFIG / "machines/thesis_wcbxfzyt.yaml"
ERRORS = CONFIG / "errors/thesis_map_demo.yaml"  # links and the 18 motion errors
ARTEFACTS = ("thesis_4ball_scaled", "thesis_4ball_map2")
# nine indexations per placement (B -60/0/60 × C 0/120/240): 180 touches, a map fit of seconds
SMALL_PLAN = {"name": "map-small", "stylus_diameter_mm": 6,
              "grid": {"b": {"start_deg": -60, "stop_deg": 60, "step_deg": 60},
                       "c": {"start_deg": 0, "stop_deg": 240, "step_deg": 120}},
              "feeds": {"probe_mm_min": 300, "approach_mm_min": 2000},
              "standoff_mm": 2, "overtravel_mm": 2, "clearance_mm": 10}
TOUCHES = 9 * 4 * 5


def truth(i: int) -> TruthModel:
    return TruthModel.from_files(MACHINE, CONFIG / f"artefacts/{ARTEFACTS[i]}.yaml", ERRORS)


def write_job(tmp) -> str:
    (tmp / "map-small.yaml").write_text(yaml.safe_dump(SMALL_PLAN), encoding="utf-8")
    job = {"name": "thesis-map-small", "placements": [
        {"name": f"P{i + 1}", "plan": "map-small.yaml",
         "artefact": str(CONFIG / f"artefacts/{a}.yaml"),
         **({"instruction": "balls on the outer rods, B1 at the front left"} if i else {})}
        for i, a in enumerate(ARTEFACTS)]}
    path = tmp / "map-job.yaml"
    path.write_text(yaml.safe_dump(job), encoding="utf-8")
    return str(path)


