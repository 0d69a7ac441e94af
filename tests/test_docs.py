"""The documentation: generated tables match their JSON, relative links and their anchors resolve, no machine
paths or internal issue numbers, the README's robot-code example runs as written, and CI runs the README's
commands."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from refiner_rt import pretrained as pt

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = [README, ROOT / "benchmarks" / "RESULTS.md", ROOT / "benchmarks" / "DATA.md",
        ROOT / "refiner_rt" / "samples" / "README.md", ROOT / "benchmarks" / "results" / "README.md",
        *sorted((ROOT / "docs").glob("*.md")),
        *sorted((ROOT / "benchmarks" / "studies").glob("**/README.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation other than '-' and '_' dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)  # '#' lines in code blocks are not headings
    return {slug(m.group(1)) for m in re.finditer(r"^#+ (.+)$", text, flags=re.M)}


def test_generated_tables_match_their_json():
    """The paper, Table 1 and speed tables are what their JSON gives. (The shipped-model tables change with every
    model that lands; `python -m benchmarks.report` rewrites them.)"""
    from models.evaluate import report
    skip = ("shipped-models", "shipped-models-short")
    for doc in report.DOCS:
        text = doc.read_text()
        assert report.render(text, skip=skip) == text, f"{doc}: run python -m benchmarks.report"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_and_anchors_resolve(doc):
    for target in LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # https:, mailto:
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        if pt.WEIGHTS_DIR.resolve() in path.parents and not pt.pretrained_models():
            continue  # the model card arrives with the first shipped model
        assert path.exists(), f"{doc.relative_to(ROOT)}: link to missing {target}"
        assert ROOT in path.parents or path == ROOT, f"{doc.relative_to(ROOT)}: link leaves the repository: {target}"
        if anchor:
            assert anchor in anchors(path), f"{doc.relative_to(ROOT)}: no heading for #{anchor} in {file or doc.name}"


def test_no_machine_paths_or_internal_issue_numbers():
    """Docs and code name paths inside the repository only, and no tracker numbers (JSON records are exempt)."""
    files = subprocess.run(["git", "-C", str(ROOT), "ls-files", "*.py", "*.md", "*.toml", ".ci/*"],
                           capture_output=True, text=True).stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    bad = re.compile(r"/work/|\.\./shared|/home/\w|\bissues? #?\d+\b", re.I)
    hits = []
    for name in files:
        if name.startswith("benchmarks/results/") or name == "tests/test_docs.py":
            continue
        path = ROOT / name
        if path.is_file():
            hits += [f"{name}:{i}: {line.strip()}" for i, line in enumerate(path.read_text().splitlines(), 1)
                     if bad.search(line)]
    assert not hits, "\n".join(hits)


def test_results_sit_in_the_folder_of_the_script_that_writes_them():
    """benchmarks/results/ holds one folder per writing script and its README, which names every folder."""
    results = ROOT / "benchmarks" / "results"
    loose = sorted(p.name for p in results.iterdir() if p.is_file() and p.name != "README.md")
    assert not loose, f"files straight in benchmarks/results/ (put them in their script's folder): {loose}"
    listed = set(re.findall(r"`(\w+)/`", (results / "README.md").read_text()))
    folders = {p.name for p in results.iterdir() if p.is_dir()}
    assert folders <= listed, f"folders benchmarks/results/README.md does not describe: {sorted(folders - listed)}"


def test_recorded_commands_are_printed_as_commands_to_rerun_now():
    """A record's script run by its path is printed as its module; a result file it wrote straight into
    benchmarks/results/ in its script's folder there; a command already in that form is kept."""
    from models.evaluate.record import current_command

    old = ("python benchmarks/tracking.py --data data/t --json benchmarks/results/tracking.json "
           "--plot=benchmarks/results/tracking.png")
    new = current_command(old)
    assert new == ("python -m benchmarks.tracking --data data/t --json benchmarks/results/tracking/tracking.json "
                   "--plot=benchmarks/results/tracking/tracking.png")
    assert current_command(new) == new
    assert current_command("python benchmarks/studies/cascade/cascade.py --x 1") == (
        "python -m benchmarks.studies.cascade.cascade --x 1")
    assert (current_command("refiner-rt bench --cpu --json benchmarks/results/bench.json")
            == "refiner-rt bench --cpu --json benchmarks/results/bench/bench.json")
    kept = "python -m benchmarks.real --data REAL --json benchmarks/results/real/x.json --plot runs/x.png"
    assert current_command(kept) == kept
    assert current_command("python benchmarks/a.py --x 1 && python benchmarks/b.py") == (
        "python -m benchmarks.a --x 1 && python -m benchmarks.b")
    # a folder argument is kept; a file that lives in another script's folder is printed where it is
    folder = "python -m benchmarks.paper --results benchmarks/results/paper"
    assert current_command(folder) == folder
    assert current_command("python benchmarks/pose_coverage.py --json benchmarks/results/pose_coverage_real_ycbv_dev.json"
                           ) == ("python -m benchmarks.pose_coverage --json "
                                 "benchmarks/results/real/pose_coverage_real_ycbv_dev.json")


def test_generated_documents_print_scripts_as_modules():
    """The model card and the paper experiments' tables print the commands as they are run now (python -m)."""
    from models.evaluate import report

    for doc in (ROOT / "refiner_rt" / "weights" / "MODELS.md", ROOT / "benchmarks" / "results" / "paper" / "tables.md",
                *report.DOCS):
        assert not re.search(r"python benchmarks/\S+\.py", doc.read_text()), f"{doc}: python benchmarks/X.py"


DESIGN = ROOT / "docs" / "design.md"
# "docs/design.md §2.7", "docs/design.md section 4" (the number may follow a line break)
DESIGN_CITATION = re.compile(r"design\.md,?\s+(?:§\s*|sections?\s+)(\d+(?:\.\d+)?)")


def design_sections() -> set[str]:
    """The numbers of docs/design.md's numbered sections and subsections ("2", "2.7")."""
    text = re.sub(r"```.*?```", "", DESIGN.read_text(), flags=re.S)
    return {m.group(1) for m in re.finditer(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", text, flags=re.M)}


def _tracked(*patterns: str) -> list[str]:
    files = subprocess.run(["git", "-C", str(ROOT), "ls-files", *patterns], capture_output=True, text=True).stdout
    if not files.split():
        pytest.skip("not a git checkout")
    return files.split()


def test_design_citations_name_sections_that_exist():
    """Every "docs/design.md §N" (or "section N") in the code and docs names a section docs/design.md has, every
    "§N" inside docs/design.md too, and the design is never cited under another path."""
    sections = design_sections()
    assert {"1", "2", "3", "4", "8", "9", "10", "11"} <= sections, sorted(sections)
    bad = []
    for name in _tracked("*.py", "*.md"):
        if name == "tests/test_docs.py":
            continue
        path = ROOT / name
        if not path.is_file():
            continue
        text = path.read_text()
        cited = [m.group(1) for m in DESIGN_CITATION.finditer(text)]
        if path == DESIGN:
            cited += re.findall(r"§(\d+(?:\.\d+)?)", text)
        bad += [f"{name}: no section {n} in docs/design.md" for n in cited if n not in sections]
        for m in re.finditer(r"(\S*)design\.md", text):
            prefix = m.group(1)
            in_docs_link = name.startswith("docs/") and prefix.endswith("(")
            if not (prefix.endswith("docs/") or in_docs_link or path == DESIGN):
                line = text[: m.start()].count("\n") + 1
                bad.append(f"{name}:{line}: cites {prefix}design.md; the design is docs/design.md")
    assert not bad, "\n".join(bad)


def _readme_python_block(heading: str = "## In robot code") -> str:
    text = README.read_text()
    section = text[text.index(heading):]
    return re.search(r"```python\n(.*?)```", section, flags=re.S).group(1)


@pytest.mark.skipif("003_cracker_box" not in {m.object_id for m in pt.pretrained_models()},
                    reason="the README's example uses the shipped cracker-box model, which does not ship here")
def test_readme_robot_code_runs_as_written(tmp_path):
    code = _readme_python_block()
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    assert "q_refined" in done.stdout


@pytest.mark.skipif("003_cracker_box" not in {m.object_id for m in pt.pretrained_models()},
                    reason="the README's tracking example uses the shipped cracker-box model, which does not ship here")
def test_readme_tracking_code_runs_as_written(tmp_path):
    code = _readme_python_block("## Tracking")
    assert len(code.strip().splitlines()) <= 14, "the tracking example is meant to stay about ten lines"
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    assert "q_tracked" in done.stdout


@pytest.mark.skipif(not any("fine" in m.stages for m in pt.pretrained_models() if m.object_id == "003_cracker_box"),
                    reason="the README's cascade example uses the cracker box's fine refiner, which does not ship here")
def test_readme_cascade_code_runs_after_the_robot_code(tmp_path):
    code = _readme_python_block() + _readme_python_block("## Below the floor") + (
        "\nprint('cascade', res.q_refined, res.coarse_used, tracker.update(image, {'003_cracker_box': boxes[0]}))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    assert "cascade" in done.stdout


def test_readme_stays_a_short_read_with_one_results_table():
    """The README is read top to bottom: at most 300 lines and one generated results table; the rest lives in docs/
    and benchmarks/RESULTS.md."""
    text = README.read_text()
    assert len(text.splitlines()) <= 300, f"README.md has {len(text.splitlines())} lines; move detail to docs/"
    assert re.findall(r"<!-- generated: ([\w-]+) -->", text) == ["shipped-models-short"]


def test_readme_example_uses_a_shipped_model_with_K():
    code = _readme_python_block()
    assert 'load("003_cracker_box"' in code and "K=K" in code


def test_ci_runs_the_readme_commands():
    """.ci/run installs and tests with the README's second command, step by step."""
    text = README.read_text()
    block = re.search(r"```bash\n(.*?)```", text, flags=re.S).group(1)
    full = [line for line in block.splitlines() if "pytest" in line][0]
    steps = [shlex.split(s.strip()) for s in full.split("#")[0].split("&&")]
    ci = [shlex.split(line) for line in (ROOT / ".ci" / "run").read_text().splitlines()
          if line.strip() and not line.lstrip().startswith("#")]
    for step in steps:
        if step[:2] == ["python3", "-m"] and "venv" in step:
            assert any(c[:3] == step[:3] for c in ci), step
            continue
        # The same command, CI adding only -q (quiet pip) after 'pip install'.
        assert any([a for a in c if a != "-q" or "pytest" in c] == [a for a in step if a != "-q" or "pytest" in step]
                   for c in ci), f"{shlex.join(step)} is not in .ci/run"


def test_model_card_commands_name_no_machine_folders():
    """The model card prints each model's training command with DATA and RUN for the build machine's folders."""
    from export.release import card

    cmd = ("python -m benchmarks.data_scaling --data /srv/d/ycb9_v1 --object 003_cracker_box --config "
           "'{\"conv_channels\": [16, 32]}' --cache /srv/d/ycb9_v1/.crops --save /srv/r/v1/003_cracker_box "
           "--json /srv/r/v1/003_cracker_box.train.json --extra-train /srv/d/ycb9_v0")
    portable = card.portable_command(cmd)
    assert portable == (
        "python -m benchmarks.data_scaling --data DATA --object 003_cracker_box --config "
        "'{\"conv_channels\": [16, 32]}' --cache DATA/.crops --save RUN/003_cracker_box "
        "--json RUN/003_cracker_box.train.json --extra-train ycb9_v0")
    assert card.portable_command(portable) == portable


def test_model_card_commands_name_a_cache_or_init_elsewhere_by_placeholder():
    """A crop cache outside DATA and RUN is written CACHE; an --init checkpoint outside them RUN/<name>.init.pt (where
    the release recovers the model it starts from), INIT without --save; a record's script path as its module.
    export.release.coarse.card_command (what the studies record) gives the same."""
    from export.release import card, coarse

    cmd = ("python benchmarks/data_scaling.py --data /srv/d/ycb9_v1 --object 011_banana --cache runs/levers/cache "
           "--init /srv/old/011_banana.pt --save /srv/r/v1/011_banana --json /srv/r/v1/011_banana.train.json")
    portable = card.portable_command(cmd)
    assert portable == ("python -m benchmarks.data_scaling --data DATA --object 011_banana --cache CACHE "
                        "--init RUN/011_banana.init.pt --save RUN/011_banana --json RUN/011_banana.train.json")
    assert card.portable_command(portable) == portable
    inside = "python -m benchmarks.data_scaling --data /d --cache /r/c --init /r/a/x.pt --save /r/a"
    assert card.portable_command(inside) == (
        "python -m benchmarks.data_scaling --data DATA --cache RUN/c --init RUN/a/x.pt --save RUN/a")
    assert card.portable_command("python -m m --init /srv/x.pt --cache /srv/c") == "python -m m --init INIT --cache CACHE"

    run, data = Path("/srv/r/v7"), Path("/srv/d/ycb9_robot")
    cmd = coarse.data_scaling_command(data, "011_banana", run, 300, 2500, Path("/srv/cache"), init=Path("/srv/x/a.pt"))
    printed = shlex.split(coarse.card_command(cmd))
    assert printed[:3] == ["python", "-m", "benchmarks.data_scaling"]
    assert printed[printed.index("--cache") + 1] == "CACHE"
    assert printed[printed.index("--init") + 1] == "RUN/011_banana.init.pt"
    assert not [a for a in printed if a.startswith("/")]


def test_first_stage_commands_train_on_turns_then_go_on_from_that_network():
    """An object of FIRST_STAGE trains twice: turns about its axis from scratch, then the recipe's stage from that
    checkpoint of the same split (no --init-other-set); the card prints both commands."""
    from export.release import coarse

    run, data = Path("/srv/r/v5"), Path("/srv/d/ycb9_v5")
    first = coarse.data_scaling_command(data, "002_master_chef_can", run, 200, 16000, data / ".crops",
                                        noise="twist:0:30", lr=1e-3, name="002_master_chef_can.stage1")
    assert first[first.index("--noise") + 1] == "twist:0:30" and first[first.index("--lr") + 1] == "0.001"
    assert first[first.index("--save") + 1] == str(run / "002_master_chef_can.stage1") and "--init" not in first
    second = coarse.data_scaling_command(data, "002_master_chef_can", run, 300, 16000, data / ".crops",
                                         init=run / "002_master_chef_can.stage1" / "a.pt", other_set=False)
    assert "--noise" not in second and "--init-other-set" not in second
    assert second[second.index("--save") + 1] == str(run / "002_master_chef_can")
    assert "--init-other-set" in coarse.data_scaling_command(data, "x", run, 300, 16000, data / ".crops",
                                                             init=run / "a.pt")


def test_train_command_turns_crops_in_plane_only_when_asked():
    """``inplane`` reaches data_scaling.py as ``--inplane DEG``, with the recipe's ray frame that the turns need;
    without it the command has no turns."""
    from export.release import coarse

    run, data = Path("/srv/r/v6"), Path("/srv/d/ycb9_tabletop")
    plain = coarse.data_scaling_command(data, "011_banana", run, 300, 2500, data / ".crops")
    assert "--inplane" not in plain
    turned = coarse.data_scaling_command(data, "011_banana", run, 300, 2500, data / ".crops", inplane=180.0)
    assert turned[turned.index("--inplane") + 1] == "180"
    assert turned[turned.index("--rotation-frame") + 1] == "ray"
    assert coarse.data_scaling_command(data, "011_banana", run, 300, 2500, data / ".crops", inplane=22.5)[
        turned.index("--inplane") + 1] == "22.5"


def _card_docs():
    from export.release import card as build

    docs = build.load_results()
    if not docs:
        pytest.skip("no shipped model")
    return build, docs


def test_model_card_names_the_set_each_model_was_scored_on():
    """All models scored on fresh scenes: the header names the set and the fp32 column of the training split is
    filled; one object rebuilt on its own split (no fresh evaluation): the card says which rows are which."""
    import copy

    build, docs = _card_docs()
    if not all(build._fresh(d) for d in docs):
        pytest.skip("the shipped evaluation is not the fresh-scene one")
    card = build.card_markdown(docs, {})
    fresh_set = docs[0]["eval"]["split"]["data"]
    assert f"`{fresh_set}`" in card and "for the objects with a value in the last column" not in card
    assert "fp32, training set's test scenes |" in card
    mixed = copy.deepcopy(docs)
    del mixed[0]["eval_training_split"]
    card = build.card_markdown(mixed, {})
    assert "for the objects with a value in the last column" in card
    row = next(line for line in card.splitlines() if line.startswith(f"| {mixed[0]['object_id']} |"))
    assert row.endswith(" - |")
    assert "(objects without a fresh evaluation: on their training crops, by `build`)" in card


def test_model_card_gives_the_symmetry_aware_error_beside_the_plain_one():
    """An object scored with its BOP symmetry too gets a sentence under the table; the table keeps the plain error."""
    import copy

    from models.data.objects import SCAN_FRAME_SYMMETRIES

    build, docs = _card_docs()
    plain = build.card_markdown(docs, {})
    docs = copy.deepcopy(docs)
    d = next(d for d in docs if d["object_id"] == "002_master_chef_can")
    d["eval"]["int8"].pop("symmetric", None)
    assert "scored with BOP's symmetry" not in build.card_markdown(docs, {})
    d["eval"]["int8"]["symmetric"] = {"n": 10, "mean_deg": 3.217, "median_deg": 2.9, "under_5_deg": 0.8,
                                      "under_10_deg": 0.95, "input_mean_deg": 12.1, "std_deg": 1.0,
                                      "symmetry": SCAN_FRAME_SYMMETRIES}
    card = build.card_markdown(docs, {})
    assert ("`002_master_chef_can` scored with BOP's symmetry for it (any turn about the axis [0, 0, 1] of the scan "
            "frame leaves it looking the same" in card)
    assert "INT8 mean **3.22**, median 2.90, under 5 degrees 80%, input mean 12.10" in card
    table_row = next(line for line in plain.splitlines() if line.startswith("| 002_master_chef_can |"))
    assert table_row in card


def test_shipped_models_name_no_machine_folder():
    """No metadata value of a shipped model holds an absolute path of the machine that built it (the INT8
    calibration source names its folder only)."""
    import onnx

    for m in pt.pretrained_models():
        for kind in ("int8", "fp32"):
            if not m.files.get(kind):
                continue
            props = {p.key: p.value for p in onnx.load(str(m.path(int8=kind == "int8")),
                                                       load_external_data=False).metadata_props}
            for key, value in props.items():
                assert "/work/" not in value and "/home/" not in value and "/tmp/" not in value, (m.object_id, key)


def test_model_card_says_when_a_training_time_was_not_recorded():
    """A model whose training run was scored again with ``data_scaling --resume`` has no training time: the card says
    so instead of failing or printing a made-up one."""
    import copy

    build, docs = _card_docs()
    docs = copy.deepcopy(docs)
    docs[0]["train"]["wall_s"] = None
    card = build.card_markdown(docs, {})
    assert "training time not recorded (its run was killed after saving the checkpoint" in card
    docs[0]["train"]["wall_s"] = 1234.0
    assert "training 1,234 s on one thread" in build.card_markdown(docs, {})
