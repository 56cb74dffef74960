"""Configuration files, `eifslam config`, --seed, -q/-v, the overwrite guard and the run's
provenance in report.json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

import eifslam
from eifslam.cli.config import config_yaml, read_config
from eifslam.cli.main import main as cli_main
from eifslam.errors import ConfigError
from eifslam.system.config import SlamConfig


def test_printed_defaults_load_back_to_the_defaults(tmp_path, capsys):
    assert cli_main(["config"]) == 0
    text = capsys.readouterr().out
    values = yaml.safe_load(text)
    assert list(values) == ["frontend", "tracking", "mapping", "keyframes", "loops", "smoothing", "runtime",
                            "experimental"]
    assert values["smoothing"]["mode"] == "smooth" and values["experimental"]["zm_gate_chi2"] == 9.21
    assert SlamConfig.from_dict(values) == SlamConfig()
    path = tmp_path / "defaults.yaml"
    path.write_text(text)
    assert read_config(path) == SlamConfig()
    # every setting is there, each after one comment line of help that ends with its default
    import dataclasses

    cfg = SlamConfig()
    for sec in values:
        assert set(values[sec]) == {f.name for f in dataclasses.fields(getattr(cfg, sec))}
    lines = text.splitlines()
    keys = [i for i, line in enumerate(lines) if line.startswith("  ") and not line.startswith("  #")]
    assert len(keys) == sum(len(v) for v in values.values())
    for i in keys:
        assert lines[i - 1].startswith("  # ") and "(default " in lines[i - 1]
    # the settings a user sees, and the few experimental ones
    from eifslam.system.config import setting_count

    total, outside = setting_count()
    assert total <= 40 and outside <= 15


def test_a_file_changes_what_it_names_and_is_checked(tmp_path, capsys):
    path = tmp_path / "c.yaml"
    path.write_text("smoothing:\n  mode: filter\nexperimental:\n  window: 7\n  zm_gate_chi2: 1.2e+1\n"
                    "frontend:\n  detector: orb\n")
    cfg = read_config(path)
    assert cfg.smoothing.mode == "filter" and cfg.experimental.window == 7
    assert cfg.filter.gate_chi2 == 12.0
    assert cfg.frontend.detector == "orb" and cfg.frontend.max_features == SlamConfig().frontend.max_features
    assert read_config(tmp_path / "c.yaml") == SlamConfig.from_dict(yaml.safe_load(config_yaml(cfg)))
    assert cli_main(["config", str(path)]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["experimental"]["window"] == 7
    marker = tmp_path / "pwned"
    cases = {
        "missing.yaml": None,
        "bad_yaml.yaml": "smoothing: [mode: filter\n",
        "unknown.yaml": "tracking:\n  nonsense: 1\n",
        "old_section.yaml": "system:\n  mode: filter\n",
        "range.yaml": "frontend:\n  map_fraction: 1.5\n",
        "list.yaml": "- 1\n- 2\n",
        "object.yaml": f"smoothing: !!python/object/apply:os.system ['touch {marker}']\n",
    }
    for name, text in cases.items():
        p = tmp_path / name
        if text is not None:
            p.write_text(text)
        with pytest.raises(ConfigError) as err:
            read_config(p)
        assert str(p) in str(err.value) and "\n" not in str(err.value), name
        capsys.readouterr()
        assert cli_main(["config", str(p)]) == 1
        err_lines = capsys.readouterr().err.strip().splitlines()
        assert len(err_lines) == 1 and err_lines[0].startswith("eifslam: error:") and name in err_lines[0]
    assert not marker.exists()


def _folder(tmp_path: Path, n: int) -> Path:
    import cv2
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54, width=320, height=240)
    d = tmp_path / "data"
    (d / "images").mkdir(parents=True)
    for k in range(n):
        cv2.imwrite(str(d / "images" / f"{k:06d}.png"), render_frame(scene, k))
    c = scene.camera
    (d / "camera.yaml").write_text(
        f"model: pinhole\nwidth: {c.width}\nheight: {c.height}\nfx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\n")
    return d


def test_run_with_a_config_file_records_what_reproduces_it_and_guards_its_outputs(tmp_path, capsys):
    d = _folder(tmp_path, 3)
    conf = tmp_path / "c.yaml"
    conf.write_text("smoothing:\n  mode: filter\nfrontend:\n  max_features: 800\n")
    out = tmp_path / "out"
    argv = ["run", str(d), "--out", str(out), "--config", str(conf), "--seed", "5", "--map-fraction", "0.4",
            "--no-html", "-q"]
    assert cli_main(argv) == 0
    err = capsys.readouterr().err
    assert "frames tracked" not in err and "eifslam:" not in err  # -q: no summary line, no bar
    rep = json.loads((out / "report.json").read_text())
    assert rep["eifslam_version"] == eifslam.__version__
    assert rep["command"].startswith("eifslam run ") and "--seed 5" in rep["command"]
    cfg = SlamConfig.from_dict(rep["config"])  # the full effective configuration, loadable
    assert cfg.smoothing.mode == "filter" and cfg.frontend.max_features == 800
    assert cfg.frontend.seed == 5 and cfg.frontend.map_fraction == 0.4  # options override the file
    assert cfg.experimental.window == SlamConfig().experimental.window
    # the outputs are not overwritten without --force
    assert cli_main(argv) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "--force" in lines[0] and str(out) in lines[0]
    (out / "report.json").write_text("{}")
    assert cli_main([*argv[:-1], "--force", "-v"]) == 0
    err = capsys.readouterr().err
    assert "effective configuration" in err and "max_features: 800" in err
    assert json.loads((out / "report.json").read_text())["eifslam_version"] == eifslam.__version__
    # a folder without eifslam outputs is fine
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert cli_main(["run", str(d), "--out", str(other), "--max-frames", "2", "--no-html", "-q", "--mode", "filter"]) == 0
    assert (other / "notes.txt").read_text() == "mine"
