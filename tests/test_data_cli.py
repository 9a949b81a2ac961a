"""The dataset commands: ``python -m image2sphere.data.verify`` and ``python -m image2sphere.data.fixtures``."""

from __future__ import annotations

from pathlib import Path

import pytest

from image2sphere.data.fixtures.__main__ import main as write_fixtures
from image2sphere.data.verify import main as verify


@pytest.fixture
def fixtures(published_fixtures) -> Path:
    """The session's fixtures (conftest), written by ``write_fixtures`` (its exit status 0 asserted there)."""
    return published_fixtures


def test_fixture_command_refuses_an_existing_root(fixtures, capsys):
    before = sorted(p.relative_to(fixtures) for p in fixtures.rglob("*"))
    assert write_fixtures([str(fixtures)]) == 1
    assert "already exist" in capsys.readouterr().err
    assert sorted(p.relative_to(fixtures) for p in fixtures.rglob("*")) == before  # nothing touched


def test_verify_exit_status_follows_the_report(fixtures, capsys):
    # the PASCAL3D+ fixture is complete and readable (no expected totals are published)
    assert verify(["pascal3d", str(fixtures / "PASCAL3D+_release1.1"), "--quiet",
                   "--synthetic", str(fixtures / "syn_images_cropped_bkg_overlaid")]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "train objects kept/tvmonitor" in out and out.rstrip().endswith("OK")
    # the SYMSOL and ModelNet10-SO(3) fixtures are far smaller than the releases: mismatches, status 1
    assert verify(["symsol", str(fixtures / "symsol"), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "train/cube" in out and "45000" in out and "<-- mismatch" in out and "FAILED" in out
    assert verify(["modelnet10", str(fixtures / "ModelNet10-SO3"), "--quiet", "--no-decode"]) == 1
    assert "FAILED" in capsys.readouterr().out


def test_verify_of_a_missing_dataset_says_where_to_get_it(tmp_path, capsys):
    assert verify(["pascal3d", str(tmp_path / "nowhere")]) == 1
    err = capsys.readouterr().err
    assert "nowhere" in err and "cvgl.stanford.edu" in err
    with pytest.raises(SystemExit):
        verify(["imagenet", str(tmp_path)])
