"""The runtime wheel: `pip install .` installs refiner_rt alone (its weights and demo samples), nothing else at the
top level of site-packages; the training package stays in the source checkout."""

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# What a source checkout has beside the package that a wheel build must not need (and that is slow to copy).
NOT_COPIED = (".git", ".venv", ".venv-*", "data", "runs", "build", "logs_local", "*.egg-info", "__pycache__",
              ".pytest_cache", ".crops")


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory) -> list[str]:
    pytest.importorskip("setuptools", reason="building the wheel without network needs setuptools installed")
    src = tmp_path_factory.mktemp("src") / "refiner-rt"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(*NOT_COPIED))
    out = tmp_path_factory.mktemp("wheel")
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", str(src),
                           "-w", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    (whl,) = out.glob("refiner_rt-*.whl")
    return zipfile.ZipFile(whl).namelist()


def test_the_wheel_holds_refiner_rt_alone(wheel_names):
    top = {n.split("/")[0] for n in wheel_names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"refiner_rt"}, sorted(top)
    assert not any(n.startswith(("models/", "export/", "benchmarks/", "tests/")) for n in wheel_names)
    assert not any(n.endswith((".obj", ".png")) for n in wheel_names if "/samples/" not in n), "training meshes"


def test_the_wheel_carries_every_shipped_model_and_the_demo_samples(wheel_names):
    index = json.loads((ROOT / "refiner_rt" / "weights" / "models.json").read_text())
    for m in index["models"].values():
        for name in m["files"].values():
            assert f"refiner_rt/weights/{name}" in wheel_names
    assert "refiner_rt/weights/models.json" in wheel_names and "refiner_rt/weights/frames.json" in wheel_names
    samples = json.loads((ROOT / "refiner_rt" / "samples" / "samples.json").read_text())
    for f in samples["frames"]:
        assert f"refiner_rt/samples/{f['file']}" in wheel_names
    assert "refiner_rt/cli/__init__.py" in wheel_names and "refiner_rt/cli/track.py" in wheel_names


def test_the_console_script_is_declared(wheel_names):
    assert any(n.endswith(".dist-info/entry_points.txt") for n in wheel_names)

