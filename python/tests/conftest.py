"""Shared fixtures: the repository's sample scene and scripts, and the CLI to compare with."""

import os
import pathlib
import shutil

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENE = ROOT / "data/samples/commonroad/USA_US101-4_1_T-1.xml"
CUT_IN = ROOT / "scripts/cut_in.rhai"
CUT_IN_PARAMS = {"cutter": 401, "victim": 405}


def cli_path():
    """The drivescript binary: $DRIVESCRIPT_BIN (tests/python.rs sets it), else the release
    build of this checkout."""
    p = os.environ.get("DRIVESCRIPT_BIN") or str(ROOT / "target/release/drivescript")
    return p if os.access(p, os.X_OK) else shutil.which("drivescript")


@pytest.fixture(scope="session")
def ds():
    import drivescript

    return drivescript


@pytest.fixture(scope="session")
def scene(ds):
    return ds.Scene.load(SCENE)


@pytest.fixture(scope="session")
def cut_in(ds):
    return ds.CostScript.from_file(CUT_IN, params=CUT_IN_PARAMS)


@pytest.fixture(scope="session")
def cli():
    p = cli_path()
    if p is None:
        pytest.skip("skipped: no drivescript binary (set DRIVESCRIPT_BIN or cargo build --release)")
    return p
