"""The service's configuration: the shipped TOML, INHAND_* variables, overrides and bad values."""

from __future__ import annotations

import itertools

import pytest

from inhand_tracker.service.server.config import DEFAULT_CONFIG, ServiceConfig, load_config, shipped_toml


def test_the_shipped_config_is_the_defaults_and_names_every_setting():
    assert load_config() == ServiceConfig()
    assert DEFAULT_CONFIG.read_text() == shipped_toml(), "run `inhand-tracker settings > configs/service.toml`"
    shipped = DEFAULT_CONFIG.read_text()
    assert all(
        f"\n{name} =" in shipped or f"\n# {name} =" in shipped or f"\n# [[{name}]]" in shipped
        for name in ServiceConfig.model_fields
        if name != "physics"
    )


def test_the_shipped_ros2_session_example_is_a_config_the_service_takes(tmp_path):
    lines = DEFAULT_CONFIG.read_text().splitlines()
    start = lines.index("# [[ros2_sessions]]")
    example = [line.removeprefix("# ") for line in itertools.takewhile(lambda x: x.startswith("#"), lines[start:])]
    (tmp_path / "hand.toml").write_text("ros2 = true\n" + "\n".join(example) + "\n")
    (session,) = load_config(tmp_path / "hand.toml").ros2_sessions
    assert (session.name, session.robot, session.joint_states) == ("left_hand", "allegro", "/allegro/joint_states")
    assert len(session.wrenches) == 4 and session.touch is None


def test_environment_then_overrides(monkeypatch):
    monkeypatch.setenv("INHAND_PHYSICS__SUBSTEPS", "4")
    monkeypatch.setenv("INHAND_LISTEN", "tcp/127.0.0.1:7500,tcp/127.0.0.1:7501")
    monkeypatch.setenv("INHAND_SCOUTING", "yes")
    config = load_config(device="cpu", listen=None)
    assert config.physics.substeps == 4 and config.device == "cpu" and config.scouting is True
    assert config.listen == ("tcp/127.0.0.1:7500", "tcp/127.0.0.1:7501")
    assert load_config(name="lab").name == "lab"


def test_bad_values_name_the_key_and_the_value(monkeypatch, tmp_path):
    monkeypatch.setenv("INHAND_PHYSICS__SUBSTEPS", "3")
    with pytest.raises(
        ValueError, match=r"service config physics: population.substeps: expected an even number, got 3"
    ):
        load_config()
    monkeypatch.setenv("INHAND_PHYSICS__SUBSTEPS", "eight")
    with pytest.raises(
        ValueError, match=r"service config physics.substeps: Input should be a valid integer.*got 'eight'"
    ):
        load_config()
    monkeypatch.delenv("INHAND_PHYSICS__SUBSTEPS")
    bad = tmp_path / "service.toml"
    bad.write_text('name = "x"\ngpus = 2\n')
    with pytest.raises(ValueError, match="service config gpus: Extra inputs are not permitted, got 2"):
        load_config(bad)
    with pytest.raises(ValueError, match="no such file"):
        load_config(tmp_path / "missing.toml")
