"""Algorithm 1 of the paper for every group of a population at once.

Per frame: write the robot's controls, replay the frame graph, score every world against the real
robot (eq. 3), keep the window mean since the last update (eq. 1), take the best world (eq. 2).
Every T frames the optimizer resamples and perturbs the group. Beyond the paper each estimate
carries the group's cost-weighted mean pose and covariance, the best world's mass and friction,
and a status. A group whose worlds nearly all lost the object, or whose best world disagrees with
the real robot about contact for several frames, is re-seeded around its last trusted estimate
(the last one whose best world felt the contacts the real hand felt; moved with the real hand
since, if the hand held the object then) with wider noise; when the real fingers touch nothing
at that moment the object fell, and the hypotheses are laid on the table below that estimate
instead.

The tracker reads only what a robot sends (controls, joints, touch) plus p0 and Sigma_p.

A frame is one host-to-device copy of the robot's packed inputs, one graph replay (controls,
physics, forward kinematics, cost, window, estimate: :mod:`service.capture`), and one asynchronous
device-to-host copy of the packed estimate, the frame's only wait. The update every T frames is a
second graph, enqueued behind that copy: its indices never leave the device.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from enum import IntEnum

import numpy as np
import torch

from sim_backend import HEALTH_NAN, HEALTH_OK, Population, SensorFK
from sim_backend.rotations import quat_conjugate, quat_log, quat_multiply, quat_rotate

from .capture import CapturedOps
from .cost import Cost, CostConfig, RealObservation
from .optimizers import METHODS, OptimizerConfig, duplicates, method_rows, update, wrs_pmf
from .sampling import clipped_normal, roughening_sigma, sample_poses, sample_wrenches, silverman_bandwidth

__all__ = ["Estimate", "Frame", "Status", "Tracker", "TrackerConfig", "setting_types"]

_PACKED = 58
"""Width of the packed estimate: pose 7, mean position 3, mean quaternion 4, covariance 36, cost,
mass, friction, lost fraction, contact disagreement, hand position 3."""


class Status(IntEnum):
    TRACKING = 0
    UNCERTAIN = 1
    """The population is spread wider than ``uncertain_spread``."""
    DIVERGED = 2
    """The worlds lost the object, or the real hand and the best world disagree about contact: the
    group was re-seeded this frame."""
    RECOVERING = 3
    """Re-seeded recently; not yet trusted."""


@dataclass(frozen=True)
class TrackerConfig:
    update_every: int = 15
    """T: frames between optimizer updates."""
    sigma_t: float = 0.005
    """Initial pose noise, translation standard deviation [m] (Sigma_p)."""
    sigma_r: float = 0.1
    """Initial pose noise, rotation standard deviation [rad] (Sigma_p)."""
    mass_sigma0: float = 0.25
    """Initial mass spread, as a fraction of the object's mass range."""
    friction_sigma0: float = 0.25
    """Initial friction spread, as a fraction of the friction range."""
    mass_sigma: float = 0.05
    """Exploration: mass noise per update, fraction of the range (Sigma_theta)."""
    friction_sigma: float = 0.05
    """Exploration: friction noise per update, fraction of the range (Sigma_theta)."""
    wrench_force: float = 0.05
    """Exploration: perturbation force standard deviation [N] (Sigma_v)."""
    wrench_torque: float = 0.001
    """Exploration: perturbation torque standard deviation [N m] (Sigma_v)."""
    jitter_t: float = 0.0005
    """Exploration beyond the paper: the object of every second or later copy of a world is
    displaced at an update, translation standard deviation [m]. Copies are exact, and a held
    object's pose along directions the sensors cannot see (a shift or turn about the squeeze) is
    kept by friction, so without it K=40 collapsed onto one wrong grasp outcome within a few
    updates and never left it (roughening, as in particle filters)."""
    jitter_r: float = 0.01
    """The same displacement's rotation standard deviation [rad], about the object's origin."""
    jitter_bandwidth: float = 1.0
    """Where a group's worlds disagree more than that, the displacement grows with their spread
    (RMS per axis of position and of rotation), up to sigma_t and sigma_r: a kernel of the
    population's own width, as regularised particle filters draw it. Its width is this multiple
    of Silverman's rule of thumb for K poses (0.645 of the spread at K=40, 0.41 at 4096). With
    the fixed displacement alone, a K=40 population still collapsed and drifted as one: in
    about one box track in twenty of the paper suite every world ended 40 to 80 mm off, the
    nearest no closer than the estimate. 0: jitter_t and jitter_r only."""
    estimate_lambda: float = 5.0
    """Sharpness of the cost weights behind the mean pose and covariance (as WRS's lambda)."""
    lost_fraction: float = 0.9
    """Diverged when more than this fraction of a group's worlds lost the object."""
    contact_loss_frames: int = 5
    """Diverged when the best world disagrees with the real robot about contact on at least half
    of the sensors for this many frames in a row (the real hand holds the object, no world does).
    A cost-level rule fired falsely whenever contact began: the normalised cost is not stationary
    across approach, grasp and transport."""
    uncertain_spread: float = 0.01
    """Uncertain when the weighted position spread (RMS) exceeds this [m]."""
    reseed_scale: float = 3.0
    """Re-seeding noise, as a multiple of sigma_t and sigma_r."""
    drop_sigma_t: float = 0.03
    """Re-seeding after a drop: horizontal spread of the hypotheses on the table [m] (a falling
    object bounces and rolls; the rotation spread is the re-seeding one)."""
    recover_frames: int = 20
    """Frames a re-seeded group reports RECOVERING before it is trusted again."""
    seed: int = 0
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    cost: CostConfig = field(default_factory=CostConfig)

    def __post_init__(self) -> None:
        if self.update_every < 1:
            raise ValueError(f"tracker update_every: expected >= 1 frame, got {self.update_every}")
        noise = ("sigma_t", "sigma_r", "wrench_force", "wrench_torque", "jitter_t", "jitter_r", "jitter_bandwidth")
        for name in (*noise, "mass_sigma", "friction_sigma"):
            if getattr(self, name) < 0:
                raise ValueError(f"tracker {name}: expected >= 0, got {getattr(self, name)}")


def setting_types(config: type, kinds: tuple[type, ...] = (int, float)) -> dict[str, type]:
    """The fields of the settings dataclass ``config`` whose defaults are of ``kinds``, with their
    types: what a session's overrides and ``bench accuracy --set`` may change."""
    return {f.name: type(f.default) for f in fields(config) if type(f.default) in kinds}


@dataclass
class Frame:
    """One frame from the robots of all groups (host arrays)."""

    controls: np.ndarray
    """Joint position targets, (G, D)."""
    q: np.ndarray
    """Measured joint positions, (G, D)."""
    force: np.ndarray | None = None
    """Fingertip forces in the sensor frames, (G, L, 3) [N], or None."""
    slip: np.ndarray | None = None
    slip_dir: np.ndarray | None = None
    spin: np.ndarray | None = None
    spin_sense: np.ndarray | None = None


@dataclass
class Estimate:
    """What the tracker reports for every group after a frame (host arrays)."""

    frame: int
    pose: np.ndarray
    """Best world's object pose, (G, 7): position [m], quaternion (x, y, z, w)."""
    cost: np.ndarray
    """Best world's window cost, (G,)."""
    mean_pose: np.ndarray
    """Cost-weighted mean object pose of the group, (G, 7)."""
    covariance: np.ndarray
    """Cost-weighted covariance of (position [m], rotation vector [rad]) about the mean, (G, 6, 6)."""
    mass: np.ndarray
    """Best world's object mass, (G,) [kg]."""
    friction: np.ndarray
    """Best world's object friction, (G,)."""
    lost: np.ndarray
    """Fraction of each group's worlds that lost the object, (G,)."""
    contact_disagreement: np.ndarray
    """Sensors on which the best world and the real robot disagree about contact, (G,)."""
    status: np.ndarray
    """Status per group, (G,) int (see :class:`Status`)."""


def _lowest_point(quat: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Height of the lowest of ``vertices`` (V, 3) rotated by ``quat`` (..., 4), shape (...)."""
    shape = (*quat.shape[:-1], len(vertices))
    return quat_rotate(quat[..., None, :].expand(*shape, 4), vertices.expand(*shape, 3))[..., 2].amin(-1)


class Tracker:
    """Algorithm 1 over every group of ``population`` at once.

    Groups share the config but may differ where a benchmark compares them side by side in one
    population: ``methods`` (G,) optimizer per group, ``exploration`` (G,) multiplier on the
    parameter and wrench noise, ``terms`` (G, 10) cost terms switched on.
    """

    def __init__(
        self,
        population: Population,
        config: TrackerConfig | None = None,
        methods: Sequence[str] | None = None,
        exploration: Sequence[float] | None = None,
        terms: np.ndarray | None = None,
    ):
        self.pop = pop = population
        self.config = cfg = config or TrackerConfig()
        self.G, self.K, self.D, self.L = pop.G, pop.K, pop.D, pop.L
        dev = self.device = pop.torch_device
        self.gen = torch.Generator(device=dev)
        self.gen.manual_seed(cfg.seed)
        self.methods = tuple(methods) if methods is not None else (cfg.optimizer.method,) * self.G
        if len(self.methods) != self.G or not set(self.methods) <= set(METHODS):
            raise ValueError(f"tracker methods: expected {self.G} of {METHODS}, got {self.methods}")
        self._olp = torch.tensor([m == "OLP" for m in self.methods], device=dev)
        scale = np.ones(self.G) if exploration is None else np.asarray(exploration, dtype=np.float64)
        if scale.shape != (self.G,) or (scale < 0).any():
            raise ValueError(f"tracker exploration: expected {self.G} multipliers >= 0, got {scale}")
        self._exploration = torch.as_tensor(scale, dtype=torch.float32, device=dev)
        if terms is not None and np.shape(terms) != (self.G, 10):
            raise ValueError(f"tracker terms: expected shape ({self.G}, 10), got {np.shape(terms)}")
        enabled = None if terms is None else torch.as_tensor(np.asarray(terms, dtype=bool), device=dev)
        self.cost = Cost(cfg.cost, self.G, dev, enabled=enabled)
        self.fk = SensorFK(pop.robot_spec, self.G, pop.device)
        self._allocate_io()
        self.window = torch.zeros(self.G, self.K, device=dev)
        """Sum of each world's cost since the last update, (G, K)."""
        self._window_frames = torch.zeros((), device=dev)
        """Frames in the window, on the device (the captured frame counts them)."""
        self.window_frames = 0
        """The same count on the host, which schedules the update."""
        self.frame = 0
        self._rows = method_rows(self.methods, dev)
        # Made here, not in the captured update: a tensor from host numbers is a copy a graph cannot hold.
        self._jitter_floor = torch.tensor([cfg.jitter_t] * 3 + [cfg.jitter_r] * 3, device=dev).view(1, 1, 6)
        ceiling = [max(cfg.sigma_t, cfg.jitter_t), max(cfg.sigma_r, cfg.jitter_r)]
        self._jitter_ceiling = torch.tensor(ceiling, device=dev)
        self._origin = torch.tensor([0.0] * 6 + [1.0], device=dev)
        """The pose that stands in for a NaN world's in the estimate's sums, (7,)."""
        self._bandwidth = cfg.jitter_bandwidth * silverman_bandwidth(self.K)
        self._frame_graph = CapturedOps(self._frame_ops, pop.device)
        self._update_graph = CapturedOps(self._update_ops, pop.device, generator=self.gen, pool=self._frame_graph)
        obj = pop.object
        self._mass_range, self._friction_range = obj.mass_range, obj.friction_range
        self._status = np.zeros(self.G, dtype=np.int64)
        self._recovering = np.zeros(self.G, dtype=np.int64)
        self._contact_loss = np.zeros(self.G, dtype=np.int64)
        self._hull = torch.as_tensor(obj.mesh.convex_hull.vertices, dtype=torch.float32, device=dev)
        """The object's hull vertices in its frame, (V, 3) [m]: where it rests when it falls."""
        self._trusted: np.ndarray | None = None
        """Best pose at the last trusted frame (tracking, or with a best world that agrees with the
        real hand on every sensor), (G, 7): where a diverged group is re-seeded."""
        self._trusted_hand = np.zeros((self.G, 3), np.float32)
        """The real hand's position (the mean of its sensor positions) at the last trusted frame, (G, 3) [m]."""
        self._trusted_held = np.zeros(self.G, bool)
        """Whether the real hand touched the object at the last trusted frame, (G,)."""

    # ------------------------------------------------------------------ start
    def start(
        self, p0: np.ndarray, q0: np.ndarray, sigma_t=None, sigma_r=None, groups: np.ndarray | None = None
    ) -> None:
        """Seed groups around their initial pose estimates ``p0`` (G, 7) with the robots at ``q0`` (G, D).

        sigma_t [m], sigma_r [rad]: Sigma_p, scalars or (G,); default from the config. ``groups``
        (G,) bool restarts only those (a service opening one session); default all, which also
        restarts the frame count and the update window.
        """
        cfg = self.config
        p0 = np.asarray(p0, dtype=np.float32).reshape(self.G, 7)
        mask = np.ones(self.G, bool) if groups is None else np.asarray(groups, bool)
        if self._trusted is None:
            self._trusted = p0.copy()
        self._trusted[mask] = p0[mask]
        self._trusted_held[mask] = False
        if groups is None:
            self.frame = self.window_frames = 0
            self._window_frames.zero_()
        self.cost.reset(torch.as_tensor(mask, device=self.device))
        self._seed(mask, p0, q0, cfg.sigma_t if sigma_t is None else sigma_t,
                   cfg.sigma_r if sigma_r is None else sigma_r)  # fmt: skip
        self._status[mask] = Status.TRACKING
        self._recovering[mask] = 0
        self._contact_loss[mask] = 0

    def set_method(self, group: int, method: str) -> None:
        """Change one group's optimizer (a service reusing a group for another session)."""
        if method not in METHODS:
            raise ValueError(f"tracker method: expected one of {METHODS}, got {method!r}")
        methods = list(self.methods)
        methods[group] = method
        if set(methods) != set(self.methods):
            self._update_graph.invalidate()  # the update runs other optimizers now
        self.methods = tuple(methods)
        self._olp[group] = method == "OLP"
        for name, rows in method_rows(self.methods, self.device).items():
            self._rows[name].copy_(rows)

    def _seed(
        self, groups: np.ndarray, mean: np.ndarray, q: np.ndarray, sigma_t, sigma_r, on_table: bool = False
    ) -> None:
        """Sample poses and physics for the worlds of ``groups`` (G,) bool and reset them.

        ``on_table``: the object fell out of the hand; each hypothesis keeps its sampled x, y and
        rotation and is put at rest on the table (its lowest point 2 mm above it)."""
        cfg, dev = self.config, self.device
        mean_t = torch.as_tensor(mean, dtype=torch.float32, device=dev)
        poses = sample_poses(mean_t, sigma_t, sigma_r, self.K, self.gen)
        (m_lo, m_hi), (f_lo, f_hi) = self._mass_range, self._friction_range
        obj = self.pop.object
        nominal_mass = torch.full((self.G, self.K), obj.mass, device=dev)
        nominal_friction = torch.full((self.G, self.K), obj.friction, device=dev)
        mass = clipped_normal(nominal_mass, cfg.mass_sigma0 * (m_hi - m_lo), m_lo, m_hi, self.gen)
        friction = clipped_normal(nominal_friction, cfg.friction_sigma0 * (f_hi - f_lo), f_lo, f_hi, self.gen)
        # OLP (and any single world) simulates the estimate itself with the nominal physics.
        open_loop = (self._olp | (self.K == 1))[:, None]
        poses = torch.where(open_loop[..., None], mean_t[:, None], poses)
        if on_table:
            poses[..., 2] = 0.002 - _lowest_point(poses[..., 3:], self._hull)
        mass = torch.where(open_loop, nominal_mass, mass)
        friction = torch.where(open_loop, nominal_friction, friction)
        sel = torch.as_tensor(groups, device=dev)[:, None]
        mass = torch.where(sel, mass, self.pop.mass)
        friction = torch.where(sel, friction, self.pop.friction)
        self.pop.reset_state(poses, np.asarray(q, dtype=np.float32).reshape(self.G, self.D), groups=groups)
        self.pop.set_params(mass=mass, friction=friction)
        self.window.masked_fill_(sel, 0.0)

    # ------------------------------------------------------------------ frame
    def _allocate_io(self) -> None:
        """The packed input and estimate buffers, and the real observation as views of the input.

        A robot frame travels as one (G, 2D + 8L + 3) row per group: controls, q, force, slip,
        slip_dir, spin, spin_sense, then the has_force, has_slip, has_spin flags."""
        G, D, L, dev = self.G, self.D, self.L, self.device
        self._fields = {"controls": (D,), "q": (D,), "force": (L, 3), "slip": (L,), "slip_dir": (L, 2),
                        "spin": (L,), "spin_sense": (L,)}  # fmt: skip
        widths = [int(np.prod(shape)) for shape in self._fields.values()]
        self._columns = dict(zip(self._fields, np.cumsum([0, *widths[:-1]]).tolist(), strict=True))
        flags = sum(widths)
        self._flag = {"force": flags, "slip": flags + 1, "spin": flags + 2}
        pinned = dev.type == "cuda"
        self._host_in = torch.zeros(G, flags + 3, pin_memory=pinned)
        self._inputs = self._host_in.to(dev) if pinned else self._host_in
        self._staged = self._host_in.numpy()

        def view(name: str) -> torch.Tensor:
            c = self._columns[name]
            return self._inputs[:, c : c + int(np.prod(self._fields[name]))].unflatten(1, self._fields[name])

        self._controls = view("controls")
        self.real = RealObservation(
            q=view("q"), sensor_pos=self.fk.pos, sensor_rot=self.fk.rot, force=view("force"),
            slip=view("slip"), slip_dir=view("slip_dir"), spin=view("spin"), spin_sense=view("spin_sense"),
            has_force=self._inputs[:, flags], has_slip=self._inputs[:, flags + 1], has_spin=self._inputs[:, flags + 2],
        )  # fmt: skip
        self._packed = torch.zeros(G, _PACKED, device=dev)
        self._host_out = torch.zeros(G, _PACKED, pin_memory=pinned)
        self._fetched = torch.cuda.Event() if pinned else None

    def _stage(self, frame: Frame) -> None:
        """Check the frame and write it into the host staging row; refuses before anything moves."""
        rows: list[tuple[str, np.ndarray]] = []
        for name, shape in self._fields.items():
            value = getattr(frame, name)
            if value is None:
                continue
            arr = np.asarray(value, dtype=np.float32)
            if arr.shape != (self.G, *shape):
                raise ValueError(f"frame {name}: expected shape {(self.G, *shape)}, got {arr.shape}")
            bad = ~np.isfinite(arr)
            if bad.any():
                at = np.argwhere(bad)[0]
                joint = name in ("controls", "q")
                where = f"joint '{self.pop.layout.joint_names[at[1]]}'" if joint else f"index {tuple(at[1:])}"
                raise ValueError(
                    f"frame {name}: {int(bad.sum())} non-finite, first at group {at[0]} {where}: {arr[tuple(at)]}"
                )
            rows.append((name, arr.reshape(self.G, -1)))
        for name in ("controls", "q"):
            if getattr(frame, name) is None:
                raise ValueError(f"frame {name}: required, got None")
        for name, arr in rows:
            c = self._columns[name]
            self._staged[:, c : c + arr.shape[1]] = arr
        for name, col in self._flag.items():
            self._staged[:, col] = float(getattr(frame, name) is not None)

    def step(self, frame: Frame) -> Estimate:
        """Advance every group by one robot frame and return the estimates."""
        if self._trusted is None:
            raise ValueError("tracker: call start(p0, q0) before the first frame")
        self._stage(frame)  # everything that can refuse the frame runs before the population moves
        with self.pop.on_stream():
            if self._inputs is not self._host_in:
                self._inputs.copy_(self._host_in, non_blocking=True)
            self._frame_graph()
            self._host_out.copy_(self._packed, non_blocking=True)
            if self._fetched is not None:
                self._fetched.record()
        self.frame += 1
        self.window_frames += 1
        if self.window_frames >= self.config.update_every:
            self._update_graph()  # queued behind the copy: the host does not wait for it
            self.window_frames = 0
        if self._fetched is not None:
            self._fetched.synchronize()  # the one wait of the frame: the estimate itself
        packed = self._host_out.numpy().copy()
        estimate = self._unpack(packed)
        self._watch(estimate, frame, hand=packed[:, 55:58])
        return estimate

    def _frame_ops(self) -> None:
        """The captured frame: controls in, physics, forward kinematics of the real joints, cost,
        window and the packed estimate out."""
        pop = self.pop
        pop.write_targets(self._controls)
        pop.step()
        self.fk.update(self.real.q)
        cost = self.cost(pop.obs, self.real)
        # A world that lost its object is worst, and one that went NaN worse still: when every
        # world has lost the object (the hand let go and rose), the argmin must not pick a NaN pose.
        cost = torch.nan_to_num(cost, nan=1e9).masked_fill_(pop.obs.health != HEALTH_OK, 1e9)
        cost.masked_fill_(pop.obs.health == HEALTH_NAN, 2e9)
        self.window += cost
        self._window_frames += 1
        self._packed.copy_(self._summary(self.window / self._window_frames))

    def _summary(self, window: torch.Tensor) -> torch.Tensor:
        """Everything the estimate needs, packed in one (G, _PACKED) tensor for one device->host copy."""
        obs, pop = self.pop.obs, self.pop
        best = window.argmin(-1)
        take = lambda t: torch.gather(t, 1, best[:, None, None].expand(-1, 1, t.shape[-1]))[:, 0]  # noqa: E731
        # A NaN world weighs nothing, but 0 * NaN is NaN: its pose must not reach the sums.
        poses = torch.where(torch.isfinite(obs.object_pose).all(-1, keepdim=True), obs.object_pose, self._origin)
        pose = take(poses)
        weights = wrs_pmf(window, self.config.estimate_lambda)  # (G, K)
        position = poses[..., :3]
        quat = poses[..., 3:]
        # Align every quaternion with the best one's hemisphere, then average (fine for spreads << 1 rad).
        quat = torch.where((quat * pose[:, None, 3:]).sum(-1, keepdim=True) < 0, -quat, quat)
        mean_p = (weights[..., None] * position).sum(1)
        mean_q = torch.nn.functional.normalize((weights[..., None] * quat).sum(1), dim=-1)
        delta = torch.cat(
            [
                position - mean_p[:, None],
                quat_log(quat_multiply(quat_conjugate(mean_q)[:, None].expand_as(quat), quat)),
            ],
            dim=-1,
        )
        cov = torch.einsum("gk,gki,gkj->gij", weights, delta, delta).reshape(self.G, 36)
        lost = (obs.health != HEALTH_OK).float().mean(-1, keepdim=True)
        disagree = self.cost.last_terms[..., 3].gather(1, best[:, None])  # sensors in contact disagreement
        scalars = torch.stack(
            [window.gather(1, best[:, None])[:, 0], pop.mass.gather(1, best[:, None])[:, 0],
             pop.friction.gather(1, best[:, None])[:, 0]], dim=-1)  # fmt: skip
        hand = self.real.sensor_pos.mean(1)
        return torch.cat([pose, mean_p, mean_q, cov, scalars, lost, disagree, hand], dim=-1)

    def _unpack(self, a: np.ndarray) -> Estimate:
        return Estimate(
            frame=self.frame,
            pose=a[:, 0:7],
            mean_pose=a[:, 7:14],
            covariance=a[:, 14:50].reshape(self.G, 6, 6),
            cost=a[:, 50],
            mass=a[:, 51],
            friction=a[:, 52],
            lost=a[:, 53],
            contact_disagreement=a[:, 54],
            status=self._status.copy(),
        )

    def _update_ops(self) -> None:
        """The captured update: the optimizer's resample and perturbation; the window starts again."""
        cfg = self.config
        window = self.window / self._window_frames
        upd = update(window, cfg.optimizer, self.gen, self.methods, self._rows)
        self.pop.resample(upd.index, check=False)
        if not set(self.methods) <= {"OLP", "EYE"}:
            explore, scale = upd.explore, self._exploration[:, None]
            mass = self._explore(self.pop.mass, cfg.mass_sigma * scale, self._mass_range, explore)
            friction = self._explore(self.pop.friction, cfg.friction_sigma * scale, self._friction_range, explore)
            self.pop.set_params(mass=mass, friction=friction, check=False)
            wrench = sample_wrenches((self.G, self.K), cfg.wrench_force, cfg.wrench_torque, self.gen, self.device)
            self.pop.set_wrench(wrench * (explore[..., None] * scale[..., None]))
            if cfg.jitter_t > 0 or cfg.jitter_r > 0 or self._bandwidth > 0:
                unit = torch.randn((self.G, self.K, 6), generator=self.gen, device=self.device)
                shift = unit * self._jitter_sigma(upd.index)
                # Only extra copies move: each surviving world keeps one copy where it was, so the
                # estimate does not jitter with the spread it buys.
                moved = explore & duplicates(upd.index)
                self.pop.displace_object(shift * (moved[..., None] * scale[..., None]))
        self.window.zero_()
        self._window_frames.zero_()

    def _jitter_sigma(self, index: torch.Tensor) -> torch.Tensor:
        """Standard deviations of the roughening after a resample ``index`` (G, K), (G, 1, 6)."""
        if self._bandwidth <= 0:
            return self._jitter_floor.expand(self.G, 1, 6)
        pose = self.pop.obs.object_pose.gather(1, index[..., None].expand(-1, -1, 7))  # the resampled worlds
        return roughening_sigma(pose, self._bandwidth, self._jitter_floor, self._jitter_ceiling)

    def _explore(self, value: torch.Tensor, sigma: torch.Tensor, bounds: tuple[float, float], mask: torch.Tensor):
        """theta ~ N(theta, Sigma_theta) clipped to its range, where ``mask``; ``sigma`` is a fraction of the range."""
        lo, hi = bounds
        return torch.where(mask, clipped_normal(value.clone(), sigma * (hi - lo), lo, hi, self.gen), value)

    # ------------------------------------------------------------------ divergence
    def _watch(self, est: Estimate, frame: Frame, hand: np.ndarray) -> None:
        """Host-side status from the estimate just copied back; re-seed diverged groups. ``hand``:
        the real hand's position this frame, (G, 3) [m], copied back with the estimate."""
        cfg = self.config
        self._recovering = np.maximum(self._recovering - 1, 0)
        recovering = self._recovering > 0
        lost_contact = ~recovering & (est.contact_disagreement >= 0.5 * self.L)
        self._contact_loss = np.where(lost_contact, self._contact_loss + 1, 0)
        diverged = (est.lost > cfg.lost_fraction) | (self._contact_loss >= cfg.contact_loss_frames)
        spread = np.sqrt(np.trace(est.covariance[:, :3, :3], axis1=1, axis2=2))
        status = np.where(spread > cfg.uncertain_spread, Status.UNCERTAIN, Status.TRACKING)
        status = np.where(recovering, Status.RECOVERING, status)
        status = np.where(diverged, Status.DIVERGED, status)
        touching = np.zeros(self.G, bool)
        if frame.force is not None:
            touching = (np.linalg.norm(frame.force, axis=-1) > cfg.cost.contact_threshold).any(-1)
        # The re-seed anchor is the best pose of the last frame on which the best world felt what
        # the real hand felt. A tracking frame whose best world already misses the real contacts
        # does not count: the contact-loss rule takes a few frames to call the divergence, and
        # those frames' pose (the object knocked out of every simulated hand) made the anchor. An
        # uncertain frame whose best world agrees on every sensor does count: a grasp that only
        # a few worlds made is uncertain until the lift, and anchoring before it put the
        # hypotheses back on the table under the lifted object.
        tracking = (status == Status.TRACKING) & ~lost_contact
        trusted = tracking | (~diverged & (est.contact_disagreement == 0))
        self._trusted[trusted] = est.pose[trusted]
        self._trusted_hand[trusted] = hand[trusted]
        self._trusted_held[trusted] = touching[trusted]
        # The real fingers touch nothing while the worlds still hold the object: it fell (or was let
        # go with the worlds' object stuck). Around the last in-hand pose the closed simulated hand
        # would catch it again, so those hypotheses go onto the table below it.
        dropped = diverged & ~touching if frame.force is not None else np.zeros(self.G, bool)
        held = diverged & ~dropped
        sigma_r = cfg.sigma_r * cfg.reseed_scale
        if held.any():
            # An object held when last trusted went where the hand went since. Re-seeding at the
            # old place in the world put the hypotheses inside the lifted fingers, where they burst
            # out, were lost and re-seeded there again, frame after frame.
            anchor = self._trusted.copy()
            anchor[:, :3] += self._trusted_held[:, None] * (hand - self._trusted_hand)
            self._seed(held, anchor, frame.q, cfg.sigma_t * cfg.reseed_scale, sigma_r)
        if dropped.any():
            self._seed(dropped, self._trusted, frame.q, cfg.drop_sigma_t, sigma_r, on_table=True)
        if diverged.any():
            self._recovering[diverged] = cfg.recover_frames
            self._contact_loss[diverged] = 0
        self._status[:] = status
        est.status = status.astype(np.int64)
