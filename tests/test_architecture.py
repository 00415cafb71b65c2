"""The layering the code base promises (docs/architecture.md): config is the floor, the
core never reaches up into a plug-in for its options, the scene-flow wings stay apart."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import yaml

from cli_helpers import flowslam

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "gtsam", "open3d", "kiss_icp", "numpy", "scipy")


def _imports(path: Path) -> list[str]:
    """Every module a file imports (at any depth: lazy imports count too)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.append(node.module)
    return names


def test_core_never_imports_a_plugin_except_the_registry_and_run_wiring():
    wiring = {"registry.py", "run.py"}
    offenders = [
        f"{p.relative_to(ROOT)}: {name}"
        for p in (ROOT / "flowslam").rglob("*.py") if p.name not in wiring
        for name in _imports(p) if name.startswith(("flowslam.frontends", "flowslam.backends"))
    ]
    assert offenders == []


def test_the_config_layer_imports_only_pydantic_and_yaml():
    for p in (ROOT / "flowslam" / "config").glob("*.py"):
        for name in _imports(p):
            assert name.split(".")[0] in ("__future__", "pathlib", "typing", "textwrap", "pydantic", "yaml") \
                or name.startswith(("flowslam.config", "flowslam.errors")), f"{p.name} imports {name}"
    code = f"import sys, flowslam.config; print([m for m in sys.modules if m.split('.')[0] in {HEAVY!r}])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_test_time_geometry_wing_does_not_import_torch():
    for p in (ROOT / "flowslam" / "sceneflow" / "refinement").glob("*.py"):
        assert not [n for n in _imports(p) if n.split(".")[0] == "torch" or ".network" in n], p.name


def test_flowslam_config_describes_every_field_and_loads_back(tmp_path):
    from flowslam.config import PipelineConfig, load_config, missing_descriptions

    assert missing_descriptions(PipelineConfig) == []
    proc = flowslam("config")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    for k, line in enumerate(lines):  # every key has a comment line right above it
        if not line.lstrip().startswith("#"):
            assert k > 0 and lines[k - 1].lstrip().startswith("#"), line
    (tmp_path / "c.yaml").write_text(proc.stdout)
    assert load_config(tmp_path / "c.yaml") == load_config()


def test_variant_is_loop_closure_on_or_off_and_training_reads_the_run_yaml(tmp_path):
    from flowslam.config import load_config, load_training_config

    assert load_config(variant="a-loam").loop_closure.enabled is False
    assert load_config().variant == "s-loam"
    run_yaml = tmp_path / "run.yaml"
    run_yaml.write_text(yaml.safe_dump({"frontend": "ssf", "training": {"epochs": 3, "prior_noise": {"max_yaw_deg": 2}}}))
    train = load_training_config(run_yaml, lr=1e-3)
    assert (train.epochs, train.prior_noise.max_yaw_deg, train.lr) == (3, 2.0, 1e-3)
    bare = tmp_path / "train.json"
    bare.write_text('{"epochs": 4, "batch_size": 1}')
    assert (load_training_config(bare).epochs, load_training_config(bare).batch_size) == (4, 1)
