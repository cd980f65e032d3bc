"""Parameter resolution: defaults, TOML, --set, type checks, unknown names, the saved file."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from sgpor_pipeline.config import NoParams, config_to_toml, resolve_config
from sgpor_pipeline.errors import PipelineError


@dataclass
class FitLike:
    iterations: int = 1000
    lr: float = 0.01
    sh_degree: int = 3
    mode: Literal["mcmc", "classic"] = "mcmc"
    budget: int | None = None
    enabled: bool = True
    views: list[str] = field(default_factory=list)
    path: Path = Path("x")
    reference: str = "largest"
    model: str | None = None


TYPES = {"fit": FitLike, "ingest": NoParams}


def test_defaults_file_and_overrides(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[fit]\niterations = 3000\nmode = "classic"\nviews = ["a", "b"]\n')
    config = resolve_config(TYPES, cfg, ["fit.lr=0.5", "fit.budget=20000", "fit.enabled=false", "fit.path=/tmp/p"])
    f = config["fit"]
    assert (f.iterations, f.lr, f.mode, f.budget, f.enabled, f.views) == (3000, 0.5, "classic", 20000, False,
                                                                           ["a", "b"])
    assert f.path == Path("/tmp/p") and isinstance(config["ingest"], NoParams)
    assert resolve_config(TYPES, None, ["fit.lr=1"])["fit"].lr == 1.0  # int accepted for float
    assert resolve_config(TYPES, None, ["fit.views=a,b"])["fit"].views == ["a", "b"]
    # a string parameter set to a name that reads as a number (a view called 24) keeps it as text
    named = resolve_config(TYPES, None, ["fit.reference=24", "fit.path=7", "fit.model=1.5"])["fit"]
    assert named.reference == "24" and named.path == Path("7") and named.model == "1.5"
    # ... and so does a list of names (views 24 and 25)
    assert resolve_config(TYPES, None, ["fit.views=24"])["fit"].views == ["24"]
    assert resolve_config(TYPES, None, ["fit.views=24,25"])["fit"].views == ["24", "25"]
    assert resolve_config(TYPES, None, ['fit.views=["24"]'])["fit"].views == ["24"]
    # ... but a number parameter still rejects text, and an optional number keeps its number
    assert resolve_config(TYPES, None, ["fit.budget=24"])["fit"].budget == 24


def test_round_trip_of_the_saved_file(tmp_path):
    config = resolve_config(TYPES, None, ["fit.iterations=7", "fit.views=[\"v1\"]"])
    path = tmp_path / "saved.toml"
    path.write_text(config_to_toml(config))
    assert resolve_config(TYPES, path) == config


@pytest.mark.parametrize("override, message", [
    ("fit.iterashuns=3", "unknown parameter 'fit.iterashuns'.*valid parameters of 'fit': budget, enabled"),
    ("fitt.iterations=3", "unknown stage 'fitt'.*valid stages: fit, ingest"),
    ("fit.iterations=3.5", "fit.iterations: expected an integer"),
    ("fit.mode=fast", "fit.mode: 'fast' is not one of 'mcmc', 'classic'"),
    ("fit.enabled=yes", "fit.enabled: expected true or false"),
    ("fit.budget=lots", "fit.budget: 'lots' is not a"),
    ("iterations=3", "--set expects STAGE.PARAM=VALUE"),
])
def test_bad_overrides(override, message):
    with pytest.raises(PipelineError, match=message):
        resolve_config(TYPES, None, [override])


def test_bad_files(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[fit\n")
    with pytest.raises(PipelineError, match="not valid TOML") as e:
        resolve_config(TYPES, bad)
    assert str(bad) in str(e.value)
    bad.write_text("[ingest]\nmax_size = 3\n")
    with pytest.raises(PipelineError, match="unknown parameter 'ingest.max_size'.*no parameters"):
        resolve_config(TYPES, bad)
    bad.write_text("fit = 3\n")
    with pytest.raises(PipelineError, match="must be a table"):
        resolve_config(TYPES, bad)
    with pytest.raises(PipelineError, match="not found"):
        resolve_config(TYPES, tmp_path / "missing.toml")


def test_set_repairs_a_bad_value_in_a_saved_file(tmp_path):
    saved = tmp_path / "config.toml"
    saved.write_text('[fit]\niterations = 3000\nmode = true\n')  # a value of the wrong type
    with pytest.raises(PipelineError, match="fit.mode"):
        resolve_config(TYPES, saved)
    f = resolve_config(TYPES, saved, ["fit.mode=classic"])["fit"]
    assert (f.mode, f.iterations) == ("classic", 3000)  # the override replaces it; the rest is read
    with pytest.raises(PipelineError, match="fit.iterations"):  # a bad override is still refused
        resolve_config(TYPES, saved, ["fit.mode=classic", "fit.iterations=lots"])


def test_a_preset_sits_under_the_file_and_the_overrides(tmp_path, monkeypatch):
    from sgpor_pipeline import presets

    monkeypatch.setitem(presets.PRESETS, "sharp", {"fit": {"iterations": 5000, "mode": "classic", "lr": 0.2}})
    monkeypatch.setitem(presets.PRESET_HELP, "sharp", "for the test")
    assert resolve_config(TYPES, preset="sharp")["fit"] == FitLike(iterations=5000, mode="classic", lr=0.2)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[fit]\niterations = 3000\n")
    f = resolve_config(TYPES, cfg, ["fit.lr=0.5"], preset="sharp")["fit"]
    assert (f.iterations, f.mode, f.lr) == (3000, "classic", 0.5)  # file and --set over the preset
    # as --set items (benchmarks/removal.py) it gives the same values
    assert resolve_config(TYPES, None, presets.as_overrides("sharp")) == resolve_config(TYPES, preset="sharp")
    assert presets.describe("sharp") == "sharp: for the test (fit.iterations=5000, fit.mode=classic, fit.lr=0.2)"
    with pytest.raises(PipelineError, match="unknown preset 'blurry'.*choose one of: .*sharp"):
        resolve_config(TYPES, preset="blurry")
    monkeypatch.setitem(presets.PRESETS, "typo", {"fit": {"iterashuns": 3}})
    with pytest.raises(PipelineError, match="unknown parameter 'fit.iterashuns'") as e:
        resolve_config(TYPES, preset="typo")
    assert "preset 'typo'" in str(e.value)


def test_every_preset_changes_real_parameters_and_a_run_records_it(tmp_path, image_dir):
    import json

    from sgpor_pipeline.dag import RunInputs, discover_stages
    from sgpor_pipeline.presets import PRESET_HELP, PRESETS
    from sgpor_pipeline.runner import CONFIG_FILE, RUN_FILE, run_pipeline

    types = {n: c.Params for n, c in discover_stages().items()}
    default = resolve_config(types)
    assert PRESETS and set(PRESETS) == set(PRESET_HELP)
    for name, tables in PRESETS.items():
        config = resolve_config(types, preset=name)
        for stage, table in tables.items():
            for key, value in table.items():
                assert getattr(config[stage], key) == value != getattr(default[stage], key), (name, stage, key)
    run_pipeline(tmp_path / "run", RunInputs(images=image_dir), until="ingest", preset="detail",
                 overrides=["finetune.hole_detail=every"])
    saved = resolve_config(types, tmp_path / "run" / CONFIG_FILE)  # the saved file repeats it without the preset
    assert saved["inpaint"].plane_interp == "cubic"
    assert saved["finetune"].hole_detail == "every"
    assert json.loads((tmp_path / "run" / RUN_FILE).read_text())["preset"] == "detail"
