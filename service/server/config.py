"""The service's configuration (pydantic-settings): defaults here, then a TOML file
(configs/service.toml), then INHAND_<KEY> environment variables (what a container sets), then
the command line. A bad value is refused with the key and the value."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import json
import os
import re
import textwrap
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from inhand_tracker.client.zenoh_session import check_endpoints
from inhand_tracker.protocol import SESSION_NAME
from inhand_tracker.protocol.keys import check_name
from inhand_tracker.service.paths import CONFIG_DIR
from inhand_tracker.sim_backend import PopulationConfig

__all__ = [
    "DEFAULT_CONFIG",
    "SERVICE_PHYSICS",
    "PhysicsSettings",
    "RosSession",
    "ServiceConfig",
    "load_config",
    "shipped_toml",
]

DEFAULT_CONFIG = CONFIG_DIR / "service.toml"

_FINGERPRINT = re.compile(r"[0-9a-f]{4}(-[0-9a-f]{4}){7}")

# Lists come from the environment comma-separated (INHAND_LISTEN=tcp/a:1,tcp/b:2), not as JSON.
Endpoints = Annotated[tuple[str, ...], NoDecode]


SERVICE_PHYSICS = (
    "substeps",
    "iterations",
    "ls_iterations",
    "tolerance",
    "ls_tolerance",
    "contacts_per_world",
    "constraints_per_world",
    "cone",
    "impratio",
    "drop_duplicate_contacts",
    "collision",
)
"""PopulationConfig's settings the service's ``[physics]`` may set: the solver's budget per frame,
the worlds' room for contacts, and the contact model (which beats the robot config's)."""


def _attribute_docs(cls: type) -> dict[str, str]:
    """The docstrings under a dataclass's fields: pydantic reads them from its own models only."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs = {}
    for field, doc in itertools.pairwise(body):
        if isinstance(field, ast.AnnAssign) and isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant):
            docs[field.target.id] = str(doc.value.value)
    return docs


class _Physics(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="after")
    def _in_range(self) -> _Physics:
        PopulationConfig(**self.model_dump())  # its own ranges, each error naming the setting
        return self

    def population(self, groups: int, worlds: int, device: str) -> PopulationConfig:
        """The population's config for ``groups`` x ``worlds`` worlds with these physics."""
        return PopulationConfig(groups=groups, worlds=worlds, device=device, **self.model_dump())


def _physics_settings() -> type[_Physics]:
    """The ``[physics]`` table's model, made from PopulationConfig's own fields (types, defaults,
    docstrings), so the two cannot drift apart."""
    hints, docs = typing.get_type_hints(PopulationConfig), _attribute_docs(PopulationConfig)
    defaults = {f.name: f.default for f in dataclasses.fields(PopulationConfig)}
    fields = {n: (hints[n], Field(defaults[n], description=docs.get(n))) for n in SERVICE_PHYSICS}
    model = create_model("PhysicsSettings", __base__=_Physics, **fields)
    model.__doc__ = "How every population simulates: PopulationConfig's settings of :data:`SERVICE_PHYSICS`."
    return model


PhysicsSettings = _physics_settings()

_TOPIC = r"^(/[A-Za-z_][A-Za-z0-9_]*)+$"
"""A ROS 2 topic, fully qualified: a launch file remaps it in the service's config."""


class RosSession(BaseModel):
    """A session the service opens itself for a robot that speaks ROS 2 and runs no client: fed from
    the robot's topics on the rmw_zenoh wire, its estimate out on ``/inhand/{name}/pose`` (with
    ``ros2``). Each joint state is a frame, with the latest command, wrenches and touch; the first
    opens the session at its joint positions, and one after the session closed opens it again."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    name: SESSION_NAME
    """The session's name, ROS name tokens joined by ``/``: its pose topic is ``/inhand/{name}/pose``,
    its TF frame ``{name}``."""
    robot: str
    """One of the service's robots (its config's ``name``)."""
    object: str
    """One of the service's objects."""
    p0: tuple[float, float, float, float, float, float, float]
    """The object's pose at the start: position [m], quaternion (x, y, z, w); a pose on ``camera``
    received before the first joint state replaces it."""
    sigma_t: float = Field(0.005, ge=0.0, le=0.1)
    """Translation noise of p0 [m]."""
    sigma_r: float = Field(0.1, ge=0.0, le=3.2)
    """Rotation noise of p0 [rad]."""
    method: str = "PBO"
    """The optimizer: OLP, EYE, WRS, REPS or PBO."""
    worlds: Annotated[int, Field(ge=1, le=65536)] | Literal["auto"] = "auto"
    """K, the session's worlds; "auto": as many as the frame budget allows (fewer taken when short)."""
    joint_states: str = Field("/joint_states", pattern=_TOPIC)
    """``sensor_msgs/msg/JointState``: the measured joint positions, by name (or in the robot
    config's order when the message names none) [rad or m]. Each message is one frame."""
    commands: str | None = Field(None, pattern=_TOPIC)
    """The joint position targets [rad or m], as ``commands_type``; unset: the measured positions."""
    commands_type: Literal["sensor_msgs/msg/JointState", "std_msgs/msg/Float64MultiArray"] = (
        "sensor_msgs/msg/JointState"
    )
    """A JointState (by name), or a Float64MultiArray (a ros2_control position controller's
    ``commands``, in ``command_joints``' order)."""
    command_joints: tuple[str, ...] = ()
    """The joints of a Float64MultiArray command, in its order; empty: the robot config's order."""
    wrenches: tuple[Annotated[str, Field(pattern=_TOPIC)], ...] = ()
    """``geometry_msgs/msg/WrenchStamped`` topics, one per fingertip sensor in the robot config's
    order: the force [N] in the sensor's frame (z the pad normal, toward the object)."""
    touch: str | None = Field(None, pattern=_TOPIC)
    """``std_msgs/msg/Float32MultiArray``: the normal force on each touch zone [N], in the robot config's order."""
    camera: str | None = Field(None, pattern=_TOPIC)
    """``geometry_msgs/msg/PoseWithCovarianceStamped``: a camera's pose of the object in the robot's
    world frame, scored as an observation."""
    camera_sigma: tuple[float, float] = (0.005, 0.05)
    """Position [m] and rotation [rad] noise of a camera pose whose covariance is all zeros."""


class ServiceConfig(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="INHAND_",
        env_nested_delimiter="__",
        extra="forbid",
        frozen=True,
        toml_file=DEFAULT_CONFIG,
        use_attribute_docstrings=True,
    )

    name: str = "default"
    """The service's name: its keys live under inhand/v7/{name}."""
    device: str = "auto"
    """auto (CUDA when present, else CPU), cpu, cuda or cuda:N."""
    listen: Endpoints = ("tcp/127.0.0.1:7447",)
    """Zenoh endpoints to listen on."""
    connect: Endpoints = ()
    """Zenoh endpoints (a router, or peers) to connect to."""
    key_file: str = "~/.local/share/inhand-tracker/service.key"
    """The service's key pair (made there on the first start, readable by its owner alone): its
    fingerprint, printed at start and in its info, is what robots are configured with
    (``TrackerClient(service_key=...)``) to know the service from any other peer."""
    zenoh_config: str | None = None
    """A Zenoh JSON5 config file under listen, connect and scouting: TLS and mTLS certificates,
    access control rules (relative to the project root)."""
    scouting: bool = False
    """Zenoh multicast scouting; off, so a service is found only where it is told to be."""
    zenoh_mode: Literal["peer", "client"] | None = None
    """How the service joins Zenoh: "peer", or "client" of the router it connects to (behind
    rmw_zenoh's router, rmw_zenohd, which relays nothing between peers). Unset: the ``zenoh_config``
    file's mode, else peer."""
    groups: int | None = Field(None, ge=1)
    """Sessions per population: sessions with the same robot, object and K share one graph replay.
    Unset: 8 on a GPU (eight sessions step at about the cost of one), 1 on a CPU (each costs its own)."""
    max_worlds: int = Field(65536, ge=1)
    """Worlds the service may hold in all."""
    max_sessions: int = Field(64, ge=1)
    """Sessions open at once at most."""
    max_opens_per_minute: int = Field(120, ge=1)
    """Sessions opened in any 60 s at most (a peer opening in a loop is refused, not served)."""
    max_sessions_per_peer: int = Field(16, ge=1)
    """Sessions open at once under one peer name (``TrackerClient(peer=...)``), so that one peer
    cannot take every slot; opens under no name count against the service's caps only."""
    max_opens_per_minute_per_peer: int = Field(30, ge=1)
    """Sessions opened in any 60 s under one peer name: a peer opening in a loop spends its own
    allowance, not the other robots'."""
    max_builds_per_minute_per_peer: int = Field(4, ge=1)
    """Populations built in any 60 s for opens under one peer name: each build takes turns with the
    running sessions' steps, so a peer opening with new settings each time is refused, not served."""
    max_populations: int = Field(16, ge=1)
    """Populations at once at most: each distinct robot, object, K and overrides builds one."""
    robot_keys: dict[str, str] = Field(default_factory=dict)
    """The robots this service keeps room for, by peer name: the fingerprint of each robot's key
    (``TrackerClient(peer=NAME, identity=FILE)``; ``inhand-tracker robot-key FILE`` prints it). An
    open under a listed name must prove that key, and the last ``reserved_sessions`` sessions and
    ``reserved_populations`` populations are theirs: no flood of other peers refuses their opens."""
    reserved_sessions: int = Field(8, ge=0)
    """Sessions kept for the robots in ``robot_keys`` (none while it is empty)."""
    reserved_populations: int = Field(2, ge=0)
    """Populations kept for the robots in ``robot_keys``, and the same share of the frame budget
    (none while it is empty)."""
    reopen_window_s: float = Field(300.0, gt=0)
    """How long a session's names (its name, its peer name) stay its robot key's after it ends, so
    that its robot's reopen finds them free [s]."""
    robots: Endpoints = ("configs/robots/allegro.toml",)
    """Robot configs (TOML; relative paths are from the project root)."""
    objects: str = "configs/objects.toml"
    """The object catalog's physics and the user's mesh objects (TOML; relative to the project root)."""
    robot_timeout_s: float = Field(3.0, gt=0)
    """A session whose robot's liveliness token is gone this long, or never came this long after
    the open, is closed and its worlds freed [s]."""
    idle_timeout_s: float = Field(60.0, gt=0)
    """A session that received no frame for this long is closed [s]."""
    seq_window: int = Field(300, ge=1)
    """A frame whose seq lies further than this from the last one re-synchronises the session to
    it (a robot that restarted its counter, or a corrupt seq) instead of being dropped as late."""
    late_resync: int = Field(15, ge=1)
    """Frames in a row behind the session's seq after which the service takes the robot's counter
    as the truth and re-synchronises to it (a stray frame ran the seq ahead): a robot is never
    silenced by its own counter."""
    model_check: float = Field(0.03, gt=0)
    """RMS difference between the worlds' joints and the robot's past which the session's status
    names a joint, and the log and the robot's next estimate say so when it joins them [rad, or m
    for a slide]: the robot config's servos are not the robot's (measured joints read with a few
    mrad of noise)."""
    max_pending: int = Field(30, ge=1)
    """Frames queued per session at most; the oldest is dropped for a new one (a robot wants its
    newest frame tracked, not a backlog)."""
    max_frame_age_s: float = Field(1.0, gt=0)
    """Frames that waited longer than this are dropped unapplied, except a session's newest [s]."""
    watchdog_s: float = Field(600.0, gt=0)
    """Once ready, the tracking loop must come round at least this often [s]; one stuck longer (in
    a step, or a population build: keep this above the slowest) takes the service down: it
    withdraws its liveliness token and `serve` exits non-zero."""
    max_observation_age_s: float = Field(0.5, gt=0)
    """A pose observation older than the newest frame by more than this (robot clock) is dropped
    and counted stale; a younger one is scored against the worlds at the next step [s]."""
    max_wait_s: float = Field(0.05, ge=0)
    """A population steps when every session sent a frame, or when a frame waited this long [s]."""
    physics: PhysicsSettings = PhysicsSettings()  # type: ignore[valid-type]
    """The tracker's physics, shared by every population (``[physics]`` in the TOML file,
    INHAND_PHYSICS__<KEY> in the environment)."""
    rate_hz: float | None = Field(None, ge=0)
    """The robots' frame rate the service keeps up with [Hz]: a new population is admitted only
    while the p99 steps of all populations together fit in ``budget_share`` of one frame period.
    0: no budget (offline replay as fast as it goes; ``worlds="auto"`` is then the paper's 40).
    Unset: 30 on a GPU; 10 on a CPU, where a frame of a few dozen worlds takes tens of milliseconds."""
    budget_share: float = Field(0.8, gt=0, le=1)
    """The share of a frame period the populations' steps may take; the rest is headroom for
    decoding, publishing and jitter."""
    min_worlds: int = Field(8, ge=1)
    """The fewest worlds a budget grants a session (``worlds="auto"``, or ``allow_fewer``); below
    it the open is refused: too few hypotheses do not track."""
    frame_time_cache: str = "~/.cache/inhand-tracker"
    """Where the step times measured on this device are kept between starts."""
    ros2: bool = False
    """Publish every session's estimate as a ROS 2 topic the way rmw_zenoh does
    (``/inhand/<session name>/pose``, ``geometry_msgs/msg/PoseWithCovarianceStamped``): a ROS 2
    stack on rmw_zenoh connected to the same Zenoh network sees it without a bridge."""
    ros2_domain_id: int | None = Field(None, ge=0, le=232)
    """The ROS 2 domain the topics are published in. Unset: ``ROS_DOMAIN_ID`` from the environment,
    as every ROS 2 node reads it, else 0."""
    ros2_frame_id: str = "world"
    """The ROS frame the poses are in: the robot's world frame (its config's base) as your TF tree names it."""
    ros2_tf: bool = False
    """Also broadcast each session's object frame (the session's name) on ``/tf`` under ``ros2_frame_id``."""
    ros2_sessions: tuple[RosSession, ...] = ()
    """Sessions fed from ROS 2 topics, one ``[[ros2_sessions]]`` table each (see RosSession): a robot
    on ROS 2 needs no client. Their poses go out on ROS 2 topics with ``ros2``."""
    view_port: int | None = Field(None, ge=1, le=65535)
    """Serve a live view of the sessions on this port (Newton's viser viewer; open it in a browser)."""
    view_host: str = "127.0.0.1"
    """Where the live view listens: 0.0.0.0 to reach it from other machines."""
    record: str | None = None
    """A folder to record every session to, one rosbag2 folder each (``<name>_<session>/``, MCAP):
    what the robot sent, every estimate and a summary of the population, for ``ros2 bag``, Foxglove
    and ``inhand-tracker replay``."""

    @property
    def ros2_domain(self) -> int:
        """The ROS 2 domain: ``ros2_domain_id``, else ``ROS_DOMAIN_ID``, else 0; a ValueError names a bad one."""
        if self.ros2_domain_id is not None:
            return self.ros2_domain_id
        text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
        if not text.isdigit() or int(text) > 232:
            raise ValueError(f"service config ros2_domain_id: ROS_DOMAIN_ID is '{text}', expected 0 to 232")
        return int(text)

    @field_validator("listen", "connect", "robots", mode="before")
    @classmethod
    def _split(cls, value: Any) -> Any:
        if isinstance(value, str):
            return tuple(v for v in value.split(",") if v)
        return value

    @field_validator("robot_keys")
    @classmethod
    def _fingerprints(cls, keys: dict[str, str]) -> dict[str, str]:
        spelled = {}
        for name, key in keys.items():
            check_name("peer", name)
            fp = key.strip().lower().replace(":", "-")
            if not _FINGERPRINT.fullmatch(fp):
                raise ValueError(f"'{name}': expected a robot key's fingerprint, 8 groups of 4 hex digits, got {key!r}")
            spelled[name] = fp
        return spelled

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...], info) -> tuple[str, ...]:
        return tuple(check_endpoints(value, info.field_name))

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # The command line (given as keyword arguments) over the environment over the file.
        return init_settings, env_settings, TomlConfigSettingsSource(settings_cls)


def shipped_toml() -> str:
    """configs/service.toml as it ships: every setting at its default, each with what it does (a
    test keeps the file so). Generated, not written by hand: a hand-kept file drifts from the settings."""
    lines = [
        "# The tracking service (`inhand-tracker serve`): every setting at its default. A key can also be set",
        "# from the environment as INHAND_<KEY> (lists comma-separated; [physics] as INHAND_PHYSICS__<KEY>),",
        "# and the endpoints from the command line. Generated from service/server/config.py.",
        "",
    ]
    for name, field in ServiceConfig.model_fields.items():
        if name != "physics":
            lines += _toml_entry(name, field)
    lines += ["[physics]", ""]
    for name, field in PhysicsSettings.model_fields.items():
        lines += _toml_entry(name, field)
    return "\n".join(lines).rstrip("\n") + "\n"


def _toml_entry(name: str, field) -> list[str]:
    """A setting as TOML: its description as comments, then its default (commented out when unset)."""
    text = " ".join((field.description or "").split())
    out = [f"# {line}" for line in textwrap.wrap(text, 98)]
    value = field.get_default(call_default_factory=True)
    if value == {}:  # an inline table to fill in (a [table] here would swallow the keys after it): an example
        return [*out, f'# {name} = {{ robot-1 = "d771-c60a-a2ab-c576-5733-16af-67e3-9644" }}', ""]
    if value is None:
        return [*out, f"# {name} =", ""]
    if name == "ros2_sessions":  # an array of tables, which TOML writes after every plain key: an example
        return [*out, *(f"# {line}" if line else "#" for line in _ROS2_EXAMPLE), ""]
    return [*out, f"{name} = {_toml_value(value)}", ""]


_ROS2_EXAMPLE = (
    "[[ros2_sessions]]",
    'name = "left_hand"',
    'robot = "allegro"',
    'object = "foam_brick"',
    "p0 = [0.02, -0.046, 0.025, 0.0, 0.0, 0.0, 1.0]",
    'joint_states = "/allegro/joint_states"',
    'commands = "/allegro/joint_commands"',
    'wrenches = ["/allegro/tip0/wrench", "/allegro/tip1/wrench", "/allegro/tip2/wrench", "/allegro/tip3/wrench"]',
    '# touch = "/allegro/touch"',
    '# camera = "/camera/object_pose"',
)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    return repr(value)


def load_config(path: str | os.PathLike | None = None, **overrides) -> ServiceConfig:
    """The config in ``path`` (default configs/service.toml, if present), then INHAND_* variables,
    then ``overrides`` (None values ignored). A ValueError names the key and the value."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    if not path.exists() and path != DEFAULT_CONFIG:
        raise ValueError(f"service config: no such file '{path}'")
    settings = ServiceConfig
    if path != DEFAULT_CONFIG:  # the same settings, read from another file
        config = {**ServiceConfig.model_config, "toml_file": path}
        settings = type("ServiceConfig", (ServiceConfig,), {"model_config": config})
    try:
        config = settings(**{k: v for k, v in overrides.items() if v is not None})
        config.ros2_domain  # noqa: B018 - a bad ROS_DOMAIN_ID is said at start, not when ROS 2 starts
        return config
    except ValidationError as exc:
        first = exc.errors()[0]
        key = ".".join(str(p) for p in first["loc"])
        if first["type"] == "value_error":  # a check of its own, whose message names the value
            raise ValueError(f"service config {key}: {first['ctx']['error']}") from None
        raise ValueError(f"service config {key}: {first['msg']}, got {first['input']!r}") from None
