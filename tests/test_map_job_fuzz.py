"""Map-job files as a user may write them (hypothesis): every one is loaded or refused with a
``ConfigError`` naming the file — no traceback, no silent acceptance of an unknown key."""

from __future__ import annotations

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.rigs.daemon_helpers import CONFIG
from contracts.map_job import load_map_job
from contracts.yaml_files import ConfigError

SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=True),
                    st.text(max_size=12))
KEYS = st.sampled_from(["name", "plan", "artefact", "instruction", "placements", "extra"])
PLAN = str(CONFIG / "plans/thesis_ch3_7poses.yaml")
ARTEFACT = str(CONFIG / "artefacts/thesis_4ball.yaml")
VALUES = st.one_of(SCALARS, st.just(PLAN), st.just(ARTEFACT), st.just("P1"),
                   st.lists(st.dictionaries(KEYS, SCALARS | st.just(PLAN) | st.just(ARTEFACT),
                                            max_size=5), max_size=3))


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.dictionaries(KEYS, VALUES, max_size=4))
def test_any_job_file_loads_or_is_refused_naming_the_file(tmp_path, doc):
    path = tmp_path / "job.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    try:
        job = load_map_job(path)
    except ConfigError as e:
        assert str(path) in str(e)
        return
    # accepted: only the known keys, a safe name, every placement's files loaded
    assert set(doc) <= {"name", "placements"} and job.placements
    for p in job.placements:
        assert p.plan.poses and p.artefact.balls
