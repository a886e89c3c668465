from __future__ import annotations

from pathlib import Path

import pytest

from app.cli import main
from app.config import ConfigError, FloornavConfig, PerceptionConfig, load_config

from .conftest import PROJECT_ROOT


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return path


def test_shipped_config_is_valid() -> None:
    config = load_config(PROJECT_ROOT / "config.toml")
    assert config.perception.smoothing_sigma_px == 5.0
    assert config.perception.n_superpixels == 200
    assert config.perception.compactness == 10.0


def test_defaults_without_file() -> None:
    assert load_config(None).perception.color_space == "lab"


def test_unknown_keys_are_rejected_with_their_path(tmp_path: Path) -> None:
    path = write(tmp_path, "[perception]\nsigma = 3\n[perception.safe_zone]\nleft = 0.1\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    keys = {issue.key for issue in info.value.issues}
    assert keys == {"perception.sigma", "perception.safe_zone.left"}


def test_out_of_bounds_value_names_key_and_value(tmp_path: Path) -> None:
    path = write(tmp_path, "[perception]\nsmoothing_sigma_px = 50\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    (issue,) = info.value.issues
    assert issue.key == "perception.smoothing_sigma_px"
    assert "50" in issue.message


def test_inverted_safe_zone_is_rejected(tmp_path: Path) -> None:
    path = write(tmp_path, "[perception.safe_zone]\ntop_y_frac = 0.9\nbottom_y_frac = 0.5\n")
    with pytest.raises(ConfigError, match="top_y_frac"):
        load_config(path)


def test_environment_overrides_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write(tmp_path, "[perception]\nsmoothing_sigma_px = 4\n")
    monkeypatch.setenv("FLOORNAV_PERCEPTION__SMOOTHING_SIGMA_PX", "2.5")
    monkeypatch.setenv("FLOORNAV_PERCEPTION__SAFE_ZONE__TOP_Y_FRAC", "0.7")
    config = load_config(path)
    assert config.perception.smoothing_sigma_px == 2.5
    assert config.perception.safe_zone.top_y_frac == 0.7


def test_bad_environment_value_names_key(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FLOORNAV_PERCEPTION__N_SUPERPIXELS", "lots")
    with pytest.raises(ConfigError) as info:
        load_config(None)
    assert info.value.issues[0].key == "perception.n_superpixels"


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(write(tmp_path, "[perception\n"))


def test_validate_config_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate-config", str(PROJECT_ROOT / "config.toml")]) == 0
    assert capsys.readouterr().out.strip() == "ok"
    bad = write(tmp_path, "[perception]\nn_superpixels = 0\nmethod = 'magic'\n")
    assert main(["validate-config", str(bad)]) == 1
    out = capsys.readouterr().out
    assert "perception.n_superpixels" in out
    assert "perception.method" in out


def test_the_shipped_configuration_is_the_models_default() -> None:
    """Tests built on FloornavConfig() run the same robot as the daemon: every key of the
    shipped config.toml equals the model's default (the file only writes them out)."""
    shipped = load_config(PROJECT_ROOT / "config.toml")
    default = FloornavConfig()
    model = default.model_dump()
    differing = [
        f"{section}.{key}: config.toml {value!r} != model {model[section][key]!r}"
        for section, values in shipped.model_dump().items()
        for key, value in values.items()
        if model[section][key] != value
    ]
    assert differing == []
    assert shipped == default
    assert shipped.perception == PerceptionConfig()
    assert shipped.perception.method == "floornet"


@pytest.mark.parametrize(
    ("autostart", "backend", "starts"),
    [
        ("simulator", "sim", True),
        ("simulator", "simavr", True),
        ("simulator", "port", False),  # a real robot waits for someone to press start
        ("always", "port", True),
        (True, "port", True),  # an explicit true is "always"
        ("never", "sim", False),
        (False, "sim", False),
    ],
)
def test_a_real_uno_starts_only_when_told_explicitly(
    autostart: object, backend: str, starts: bool
) -> None:
    config = FloornavConfig.model_validate(
        {"runtime": {"autostart": autostart}, "serial": {"backend": backend}}
    )
    assert config.autostarts() is starts


def test_autostart_names_its_choices(tmp_path: Path) -> None:
    path = tmp_path / "config.toml"
    path.write_text('[runtime]\nautostart = "yes"\n')
    with pytest.raises(ConfigError, match=r"runtime\.autostart"):
        load_config(path)
