"""The results folder's layout (difftex.layout): its paths, and that nothing else spells them.

The table below is the layout of results folders written before difftex.layout existed: a path
that changed would leave an existing folder invalid (and a second run with something to do).
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import sys
from pathlib import Path

import pytest

from difftex import layout
from difftex.layout import Results

REPO = Path(__file__).resolve().parents[1]

# (expression on Results(root), path relative to root), as the workflow and the stages wrote them
EXPECTED = [
    ("photos_json", "photos.json"),
    ("photos_csv", "photos.csv"),
    ("filter_part('{part}')", "filter/photos-{part}.json"),
    ("dense_dir", "dense"),
    ("dense_done", "dense/dense.json"),
    ("visibility_dir", "visibility"),
    ("visibility_link", "visibility.txt"),
    ("visibility('p0')", "visibility/p0.npz"),
    ("visibility_summary", "visibility/summary.json"),
    ("visibility_tile('{tile}')", "visibility/tiles/{tile}.json"),
    ("heights_dir", "heights"),
    ("heights_tile('{tile}')", "heights/tiles/{tile}.json"),
    ("crops('p0')", "init/p0/crops.npz"),
    ("job_file('initialize', '{job}')", "init/jobs/{job}.json"),
    ("transfers('p0')", "histmatch/p0/transfers.npz"),
    ("job_file('histmatch', '{job}')", "histmatch/jobs/{job}.json"),
    ("polygon_optimized('p0')", "optimized/p0"),
    ("weights('p0')", "optimized/p0/weights.npz"),
    ("optimized('p0')", "optimized/p0/optimized.npz"),
    ("stats('p0')", "optimized/p0/stats.json"),
    ("composite('p0')", "optimized/p0/composite.npz"),
    ("job_file('texture', '{job}')", "optimized/jobs/{job}.json"),
    ("job_file('optimize', '{job}')", "optimized/jobs/{job}.optimize.json"),
    ("job_file('compose', '{job}')", "optimized/jobs/{job}.compose.json"),
    ("polygon_textures('p0')", "textures/p0"),
    ("texture('p0')", "textures/p0/texture.png"),
    ("job_file('finish', '{job}')", "textures/jobs/{job}.json"),
    ("model_summary", "model/summary.json"),
    ("model_file('.obj')", "model/model.obj"),
    ("model_file('.glb')", "model/model.glb"),
    ("tileset", "model/tileset/tileset.json"),
    ("metrics", "evaluation/metrics.json"),
    ("error_map('p0')", "evaluation/error_maps/p0.png"),
    ("views_dir", "evaluation/views"),
    ("view('IMG_1.JPG', 'render')", "evaluation/views/IMG_1_render.png"),
    ("stage_config('{stage}', '{digest}')", "config/{stage}-{digest}.yaml"),
    ("compute_config", "config/compute.yaml"),
    ("log('assemble')", "logs/assemble.log"),
    ("log('initialize', '{job}')", "logs/initialize/{job}.log"),
    ("benchmark('texture', '{job}')", "benchmarks/texture/{job}.tsv"),
    ("report_md", "report.md"),
    ("report_html", "report/index.html"),
    ("peer_record", "peer.json"),
]


@pytest.mark.parametrize("expr, rel", EXPECTED)
def test_paths_are_those_of_existing_results_folders(expr, rel):
    res = Results("results/scene")
    path = eval(f"res.{expr}", {"res": res})  # the table above
    assert isinstance(path, Path)
    # the string the workflow's f"{R}/..." patterns gave, wildcards unexpanded
    assert str(path) == f"results/scene/{rel}"


def _every_path(res: Results) -> dict[str, Path]:
    """Every path Results gives, its methods called with a wildcard for each argument."""
    out = {}
    for name, member in inspect.getmembers(Results):
        if name.startswith("_") or name == "root":
            continue
        if isinstance(member, property):
            out[name] = getattr(res, name)
        elif callable(member):
            params = list(inspect.signature(member).parameters)[1:]
            if name == "job_file":
                args = ["finish", "{job}"]
            else:
                args = ["{" + p + "}" for p in params]
            out[name] = getattr(res, name)(*args)
    return out


def test_every_path_is_under_the_root(tmp_path):
    paths = _every_path(Results(tmp_path))
    assert len(paths) >= 30
    for name, path in paths.items():
        assert isinstance(path, Path), name
        assert path.is_relative_to(tmp_path) and path != tmp_path, f"{name}: {path}"


def test_every_path_is_in_the_table():
    # a new path gets a row in EXPECTED (and a line in the module's docstring)
    named = {re.match(r"\w+", expr).group(0) for expr, _ in EXPECTED}
    assert set(_every_path(Results("r"))) - {"init_dir", "histmatch_dir", "optimized_dir", "textures_dir", "model_dir",
                                             "evaluation_dir", "logs_dir", "benchmarks_dir"} <= named


def test_wildcards_stay_literal_and_a_str_root_is_a_path():
    res = Results("results/x")
    assert res == Results(Path("results/x")) and isinstance(res.root, Path)
    for rule in layout.JOB_FILES:
        assert "{job}" in str(res.job_file(rule, "{job}"))
    assert str(res.log("stage_config", "{stage}-{digest}")) == "results/x/logs/stage_config/{stage}-{digest}.log"
    with pytest.raises(dataclasses.FrozenInstanceError):  # a results folder does not move
        res.root = Path("elsewhere")


def test_the_job_files_of_different_rules_differ():
    res = Results("r")
    files = [res.job_file(rule, "j") for rule in layout.JOB_FILES]
    assert len(set(files)) == len(files)


def test_every_per_polygon_rule_lists_its_polygons_files():
    # the rules whose jobs write a polygon's files are those with a job file, and their files
    # are in the polygon's folder of the rule's results folder (difftex.workflow.products)
    assert set(layout.POLYGON_PRODUCTS) == set(layout.JOB_FILES)
    res = Results("r")
    for rule, (folder, _) in layout.POLYGON_PRODUCTS.items():
        files = layout.polygon_products(res, rule, "p0")
        assert files and all(f.parent == res.root / folder / "p0" for f in files), rule
        assert res.job_file(rule, "j").parent.parent == res.root / folder
    assert res.texture("p0") in layout.polygon_products(res, "finish", "p0")
    assert res.transfers("p0") in layout.polygon_products(res, "histmatch", "p0")
    assert res.root / "textures/p0/texture.exr" in layout.polygon_products(res, "finish", "p0", exr=True)


def test_layout_imports_only_the_standard_library():
    tree = ast.parse(Path(layout.__file__).read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    roots = {n.split(".")[0] for n in names} - {"__future__"}
    assert roots <= set(sys.stdlib_module_names), roots


# ---------------------------------------------------------------------------------------------
# Nothing but difftex/layout.py spells the layout

# the file names of layout's constants, as string literals in code ('"weights.npz"')
FILE_NAMES = sorted(v for k, v in vars(layout).items() if k.isupper() and isinstance(v, str) and "." in v)
# a results folder's subfolders joined onto a path, and the workflow's old f-string patterns
FOLDER_JOINS = [f'/ "{d}"' for d in ("optimized", "textures", "visibility", "init", "evaluation", "benchmarks",
                                      "logs", "model", "report")]
SMK_PATTERN = "{R}/"
# (file, literal): the same names, but not of a results folder
ELSEWHERE = {
    ("difftex/evaluation/peers/meshlab.py", '"texture.png"'): "the texture MeshLab writes in its work folder",
    ("difftex/evaluation/peers/texrecon.py", '/ "model"'): "texrecon's output prefix in its work folder",
}


def _code_files() -> list[Path]:
    files = [p for p in sorted((REPO / "difftex").rglob("*.py")) if p.name != "layout.py" or p.parent.name != "difftex"]
    files += sorted((REPO / "workflow").rglob("*.smk")) + sorted((REPO / "workflow").rglob("*.py"))
    return [*files, REPO / "Snakefile"]


def test_file_names_are_written_only_in_layout():
    assert {"weights.npz", "composite.npz", "stats.json", "texture.png", "summary.json"} <= set(FILE_NAMES)
    found = []
    for path in _code_files():
        rel = str(path.relative_to(REPO))
        text = path.read_text()
        literals = [f'"{n}"' for n in FILE_NAMES] + [f"'{n}'" for n in FILE_NAMES] + FOLDER_JOINS + [SMK_PATTERN]
        for lit in literals:
            if lit in text and (rel, lit) not in ELSEWHERE:
                line = text[: text.index(lit)].count("\n") + 1
                found.append(f"{rel}:{line}: {lit}")
    assert not found, "results paths spelled outside difftex/layout.py (use difftex.layout):\n" + "\n".join(found)


def test_the_exceptions_are_still_there():
    # an exception that no longer applies is dropped from ELSEWHERE
    for (rel, lit), why in ELSEWHERE.items():
        assert lit in (REPO / rel).read_text(), f"{rel}: {lit} gone ({why}); drop it from ELSEWHERE"
