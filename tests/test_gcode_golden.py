"""Golden programs per dialect for a small plan; regenerate with `make golden` and review."""

from __future__ import annotations

import pytest

from tests.regen_golden import GOLDEN, golden_files

FILES = golden_files()


@pytest.mark.parametrize("name", sorted(FILES))
def test_program_matches_golden(name):
    path = GOLDEN / name
    assert path.exists(), f"{path} missing: run `make golden`"
    want = path.read_text(encoding="ascii")
    got = FILES[name]
    if got != want:
        diff = next(i for i, (a, b) in enumerate(zip(got.splitlines(), want.splitlines(),
                                                     strict=False)) if a != b) \
            if got.splitlines()[:1] else 0
        pytest.fail(f"{name} differs from the golden file at line {diff + 1}: "
                    "run `make golden` if the change is intended and review the diff")


def test_golden_set_is_complete():
    assert sorted(p.name for p in GOLDEN.iterdir()) == sorted(FILES)
