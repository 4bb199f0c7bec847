"""Algorithm 1 of the paper for every group of a population at once.

Per frame: write the robot's controls, replay the frame graph, score every world against the real
robot (eq. 3), keep the window mean since the last update (eq. 1), take the best world (eq. 2).
Every T frames the optimizer resamples and perturbs the group. Beyond the paper each estimate
carries the group's cost-weighted mean pose and covariance, the best world's mass and friction,
and a track state; :mod:`.recovery` decides when a group has diverged and re-seeds it.

The tracker reads only what a robot sends (controls, joints, touch) plus p0 and Sigma_p.

A frame is one host-to-device copy of the robot's packed inputs, one graph replay (controls,
physics, forward kinematics, cost, window, estimate: :mod:`.capture`), and one asynchronous
device-to-host copy of the packed estimate, the frame's only wait. The update every T frames is a
second graph, enqueued behind that copy: its indices never leave the device.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
import torch

from inhand_tracker.sim_backend import HEALTH_AWAY, HEALTH_NAN, HEALTH_OK, Population, SensorFK

from .capture import CapturedOps
from .config import TrackerConfig
from .contacts import ContactExplorer, say_overflow
from .cost import TERMS, Cost, RealObservation
from .estimate import open_loop_share, pose_statistics, unresolved_variance
from .evidence import Residuals, declared_scatter, evidence_strength, pose_sources
from .joint_check import JointCheck
from .layout import ESTIMATE, Frame, GroupEstimates, InputLayout
from .observations import PoseObserver, draw_around
from .optimizers import HELD_COST, METHODS, duplicates, estimate_pmf, method_rows, open_loop_worlds, update
from .recovery import Recovery
from .sampling import (
    chance_shift,
    clipped_normal,
    lowest_point,
    perturb_within,
    recentre,
    roughening_sigma,
    sample_poses,
    sample_wrenches,
    shrink_toward_mean,
    silverman_bandwidth,
)
from .servos import ServoExplorer
from .window import CostWindow

__all__ = ["Tracker"]

log = logging.getLogger(__name__)


class Tracker:
    """Algorithm 1 over every group of ``population`` at once.

    Groups share the config but may differ where a benchmark compares them side by side in one
    population: ``methods`` (G,) optimizer per group, ``exploration`` (G,) multiplier on the
    parameter and wrench noise, ``terms`` (G, 12) cost terms switched on.
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
        self.olp = torch.tensor([m == "OLP" for m in self.methods], device=dev)
        """Which groups run the open-loop baseline, (G,) bool."""
        self.contacts = ContactExplorer(cfg.contacts, pop, self.gen)
        self.servos = ServoExplorer(cfg.servos, pop, cfg.seed)
        scale = np.ones(self.G) if exploration is None else np.asarray(exploration, dtype=np.float64)
        if scale.shape != (self.G,) or (scale < 0).any():
            raise ValueError(f"tracker exploration: expected {self.G} multipliers >= 0, got {scale}")
        self._exploration = torch.as_tensor(scale, dtype=torch.float32, device=dev)
        if terms is not None and np.shape(terms) != (self.G, TERMS):
            raise ValueError(f"tracker terms: expected shape ({self.G}, {TERMS}), got {np.shape(terms)}")
        enabled = None if terms is None else torch.as_tensor(np.asarray(terms, dtype=bool), device=dev)
        self.cost = Cost(cfg.cost, self.G, dev, enabled, (pop.robot_spec.touch_deadband, pop.robot_spec.touch_noise))
        self.fk = SensorFK(pop.robot_spec, self.G, pop.device)
        self._allocate_io()
        self.windows = CostWindow(self.G, self.K, dev)
        self.window_frames = 0
        """Frames since the last update, on the host, which schedules the next."""
        self.frame = 0
        self._rows = method_rows(self.methods, dev)
        # Made here, not in the captured update: a tensor from host numbers is a copy a graph cannot hold.
        jitter, seeding = cfg.exploration, cfg.seeding
        self._jitter_floor = torch.tensor([jitter.jitter_t] * 3 + [jitter.jitter_r] * 3, device=dev).view(1, 1, 6)
        ceiling = [max(seeding.sigma_t, jitter.jitter_t), max(seeding.sigma_r, jitter.jitter_r)]
        self._jitter_ceiling = torch.tensor(ceiling, device=dev)
        self._diagonal = np.arange(6)
        self._seeded = np.zeros((self.G, 6), np.float32)
        """Each group's variance of its latest seeding, (G, 6) [m^2, rad^2]: what its worlds sample."""
        self._origin = torch.tensor([0.0] * 6 + [1.0], device=dev)
        """The pose that stands in for a NaN world's in the estimate's sums, (7,)."""
        self._sharpness = torch.ones(self.G, 1, device=dev)
        """Each group's factor on the estimate's weights, (G, 1): how far its poses explain its costs."""
        self._anchor = open_loop_worlds(cfg.optimizer, self.K, dev)
        """Each group's open-loop world, (1, K) bool (:func:`.optimizers.open_loop_worlds`)."""
        self._first = torch.arange(self.K, device=dev)[None] == 0  # (1, K): the world an OLP group reports
        self._reckoned = torch.zeros(self.G, 3, device=dev)  # (G, 3): open_loop_share's sums and felt
        self._evidence = torch.tensor([[0.0, 1.0]], device=dev).repeat(self.G, 1)
        """Each group's last update's separation F ratio and strength on the poses, (G, 2)."""
        self.residuals = Residuals(self.G, self.D, self.L, pop.Z, dev)
        self._bandwidth = cfg.exploration.jitter_bandwidth * silverman_bandwidth(self.K)
        shrinks = 0 < cfg.exploration.jitter_shrink_worlds <= self.K and self._bandwidth < 1.0
        self._shrink = 1.0 - math.sqrt(1.0 - self._bandwidth**2) if shrinks else 0.0
        self._frame_graph = CapturedOps(self._frame_ops, pop.device)
        randoms = (self.gen, self.servos.gen)
        self._update_graph = CapturedOps(self._update_ops, pop.device, generators=randoms, pool=self._frame_graph)
        obj = pop.object
        self._mass_range, self._friction_range = obj.mass_range, obj.friction_range
        points = obj.surface_points(1000).astype(np.float64)
        falls = not pop.layout.carries_on_palm
        self.recovery = Recovery(cfg, self.G, self.L, moment=points.T @ points / len(points), falls=falls)
        self._hull = torch.as_tensor(obj.mesh.convex_hull.vertices, dtype=torch.float32, device=dev)
        """The object's hull vertices in its frame, (V, 3) [m]: where it rests when it falls."""
        self.observations = PoseObserver(cfg.observations, self.K)
        self.overflows = 0
        """Frames on which a world dropped contacts for want of room (:func:`.contacts.say_overflow`)."""
        self.recovery.open_loop[:] = self.olp.cpu().numpy()

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
        self.recovery.start(p0, mask)
        if groups is None:
            self.frame = self.window_frames = 0
            self.windows.restart()
        started = torch.as_tensor(mask, device=self.device)
        self.cost.reset(started)
        self.joints.start(started)
        self.contacts.start(started, self.olp)
        self.servos.start(started)
        # Under evidence scaling a group's first estimate weighs its worlds alike: nothing has told them apart yet.
        self._sharpness.masked_fill_(started[:, None], 0.0 if cfg.optimizer.by_evidence else 1.0)
        self._evidence[:, 0].masked_fill_(started, 0.0)
        self._evidence[:, 1].masked_fill_(started, 0.0 if cfg.optimizer.by_evidence else 1.0)
        self.residuals.start(started)
        self.seed_groups(mask, p0, q0, cfg.seeding.sigma_t if sigma_t is None else sigma_t,
                   cfg.seeding.sigma_r if sigma_r is None else sigma_r)  # fmt: skip

    def capture(self) -> None:
        """Record the frame's and the update's graphs now instead of at the first frame and the
        first update (a service builds populations beside its loop and wants its first frames on
        time). It runs a frame and an update: call :meth:`start` after it."""
        if self._frame_graph.enabled and not self._frame_graph.captured:
            with self.pop.on_stream():
                self._frame_graph()
                self._update_graph()

    @property
    def captured(self) -> bool:
        """Whether a frame is one graph replay (the frame's graph was captured)."""
        return self._frame_graph.captured

    def set_method(self, group: int, method: str) -> None:
        """Change one group's optimizer (a service reusing a group for another session)."""
        if method not in METHODS:
            raise ValueError(f"tracker method: expected one of {METHODS}, got {method!r}")
        methods = list(self.methods)
        methods[group] = method
        if set(methods) != set(self.methods):
            self._update_graph.invalidate()  # the update runs other optimizers now
        self.methods = tuple(methods)
        self.olp[group] = method == "OLP"
        self.recovery.open_loop[group] = method == "OLP"
        for name, rows in method_rows(self.methods, self.device).items():
            self._rows[name].copy_(rows)

    def seed_groups(
        self, groups: np.ndarray, mean: np.ndarray, q: np.ndarray, sigma_t, sigma_r, on_table: bool = False
    ) -> None:
        """Sample poses and physics for the worlds of ``groups`` (G,) bool and reset them.

        ``on_table``: the object fell out of the hand; each hypothesis keeps its sampled x, y and
        rotation and is put at rest on the table (its lowest point 2 mm above it)."""
        cfg, dev = self.config, self.device
        mean_t = torch.as_tensor(mean, dtype=torch.float32, device=dev)
        poses = sample_poses(mean_t, sigma_t, sigma_r, self.K, self.gen)
        var_t, var_r = (np.broadcast_to(np.square(s, dtype=np.float32), self.G) for s in (sigma_t, sigma_r))
        self._seeded[groups] = np.stack([var_t] * 3 + [var_r] * 3, axis=-1)[groups]
        (m_lo, m_hi), (f_lo, f_hi) = self._mass_range, self._friction_range
        obj = self.pop.object
        nominal_mass = torch.full((self.G, self.K), obj.mass, device=dev)
        nominal_friction = torch.full((self.G, self.K), obj.friction, device=dev)
        mass = clipped_normal(nominal_mass, cfg.seeding.mass_sigma0 * (m_hi - m_lo), m_lo, m_hi, self.gen)
        friction = clipped_normal(nominal_friction, cfg.seeding.friction_sigma0 * (f_hi - f_lo), f_lo, f_hi, self.gen)
        # OLP, a single world and a group's open-loop world simulate the estimate with the nominal physics.
        open_loop = (self.olp | (self.K == 1))[:, None] | self._anchor
        poses = torch.where(open_loop[..., None], mean_t[:, None], poses)
        if on_table:
            poses[..., 2] = 0.002 - lowest_point(poses[..., 3:], self._hull)
        mass, friction = torch.where(open_loop, nominal_mass, mass), torch.where(open_loop, nominal_friction, friction)
        sel = torch.as_tensor(groups, device=dev)[:, None]
        mass, friction = torch.where(sel, mass, self.pop.mass), torch.where(sel, friction, self.pop.friction)
        timeconst, impratio = self.contacts.seeded(sel, open_loop.expand(self.G, self.K))
        self.pop.reset_state(poses, np.asarray(q, dtype=np.float32).reshape(self.G, self.D), groups=groups)
        # A pose drawn around an object lying on a palm or a table is often a few millimetres inside it.
        self.pop.separate_object(np.repeat(np.asarray(groups, bool)[:, None], self.K, axis=1))
        self.pop.write_params(mass, friction, timeconst, impratio)  # drawn inside their ranges
        self.windows.clear(sel)
        self._reckoned.masked_fill_(sel, 0.0)

    def observe(self, group: int, pose: np.ndarray, covariance: np.ndarray) -> bool:
        """Score ``group``'s worlds against an observed object pose (7,) with its ``covariance``
        (6, 6; position [m^2], rotation vector [rad^2]) until the next update, re-seeding or
        drawing worlds around it where they disagree (:class:`.PoseObserver`). Returns whether it
        re-seeded. An open-loop group (OLP) ignores it: it simulates its start alone."""
        if bool(self.olp[group]):
            return False
        obs = self.observations
        with self.pop.on_stream():  # behind the update the last frame may have queued
            judged = obs.judge(self.pop.object_coords[group], pose, covariance)
            if judged.reseed:
                anchor, mask = np.tile(np.asarray(pose, np.float32), (self.G, 1)), np.arange(self.G) == group
                q = self.real.q.detach().cpu().numpy()
                self.seed_groups(mask, anchor, q, judged.position_sigma, judged.rotation_sigma)
                self.recovery.reseeded(anchor, mask)
                return True
            distance = judged.distance
            if judged.inject:
                observed = obs.observed(pose, self.device)
                draw_around(self.pop, self.windows, self.scored()[group], group, observed, judged, self.gen)
                distance = obs.distance(self.pop.object_coords[group], observed, obs.factor(covariance, self.device))
            self.windows.evidence[group] += obs.evidence(distance)
        return False

    # ------------------------------------------------------------------ frame
    def _allocate_io(self) -> None:
        """The packed input and estimate rows (:mod:`.layout`), and the real observation as views
        of the input row on the device."""
        G, dev = self.G, self.device
        self.inputs = InputLayout(self.D, self.L, self.pop.Z)
        pinned = dev.type == "cuda"
        self._host_in = torch.zeros(G, self.inputs.width, pin_memory=pinned)
        self._inputs = self._host_in.to(dev) if pinned else self._host_in
        self._staged = self._host_in.numpy()
        views = self.inputs.views(self._inputs)
        self._controls = views.pop("controls")
        self.real = RealObservation(sensor_pos=self.fk.pos, sensor_rot=self.fk.rot, **views)
        # The packed estimate, then each joint's RMS disagreement with the robot (the model check).
        self._packed = torch.zeros(G, ESTIMATE.width + self.D, device=dev)
        self._host_out = torch.zeros(G, ESTIMATE.width + self.D, pin_memory=pinned)
        self.joints = JointCheck(G, self.D, dev)
        self._fetched = torch.cuda.Event() if pinned else None

    def step(self, frame: Frame) -> GroupEstimates:
        """Advance every group by one robot frame and return the estimates."""
        if self.recovery.trusted is None:
            raise ValueError("tracker: call start(p0, q0) before the first frame")
        # Everything that can refuse the frame runs before the population moves.
        self.inputs.stage(frame, self._staged, self.pop.layout.joint_names)
        with self.pop.on_stream():
            if self._inputs is not self._host_in:
                self._inputs.copy_(self._host_in, non_blocking=True)
            self._frame_graph()
            self._host_out.copy_(self._packed, non_blocking=True)
            if self._fetched is not None:
                self._fetched.record()
        self.frame, self.window_frames = self.frame + 1, self.window_frames + 1
        if self.window_frames >= self.config.update_every:
            self._update_graph()  # queued behind the copy: the host does not wait for it
            self.window_frames = 0
        if self._fetched is not None:
            self._fetched.synchronize()  # the one wait of the frame: the estimate itself
        packed = self._host_out.numpy().copy()
        estimate = GroupEstimates.unpack(packed[:, : ESTIMATE.width], self.frame, self.recovery.status.copy())
        estimate.joint_rms = packed[:, ESTIMATE.width :]
        has = lambda group: self.inputs.columns.view(self._staged, f"has_{group}") > 0  # noqa: E731
        hand = ESTIMATE.view(packed, "hand")
        reseeds = self.recovery.watch(estimate, frame.force, has("force"), hand, frame.touch, has("touch"))
        estimate.reseeded = np.zeros(self.G, bool)
        for r in reseeds:
            self.seed_groups(r.groups, r.anchor, frame.q, r.sigma_t, r.sigma_r, on_table=r.on_table)
            estimate.reseeded |= r.groups
        estimate.status = self.recovery.status.copy()
        if estimate.overflow.any():
            self.overflows += 1
            if self.overflows == 1:  # once per population: every frame after would say it again
                say_overflow(np.flatnonzero(estimate.overflow), self.pop.config)
        unresolved = unresolved_variance(estimate.cost, self._seeded, self.K, self.config.estimate)
        estimate.covariance[:, self._diagonal, self._diagonal] += unresolved
        return estimate

    def _frame_ops(self) -> None:
        """The captured frame: controls in, physics, forward kinematics of the real joints, cost,
        window and the packed estimate out."""
        pop = self.pop
        pop.write_targets(self._controls)
        pop.step()
        self.fk.update(self.real.q)
        cost = self.cost(pop.obs, self.real)
        lost, feels = self._lost()
        # A world that lost its object is worst, and one that went NaN worse still: when every
        # world has lost the object, the argmin must not pick a NaN pose.
        cost = torch.nan_to_num(cost, nan=1e9).masked_fill_(lost, 1e9)
        cost.masked_fill_(pop.obs.health == HEALTH_NAN, 2e9)
        self.windows.add(cost)
        self.joints.update(pop.obs.q, self.real.q)
        self._packed[:, : ESTIMATE.width].copy_(self._summary(self.scored(), lost, feels))
        self._packed[:, ESTIMATE.width :].copy_(self.joints.rms())

    def _lost(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Which worlds lost their object, (G, K) bool, and whether the robot feels it, (G,) bool. Away from the
        hand it is lost only while the real hand feels it, or cannot say (no force or touch sensing; a palm that
        carries objects and has no touch zones): once the real fingers touch nothing it may lie on the table,
        put down or dropped, and counting it lost there re-seeded every frame after a drop."""
        health, real, threshold = self.pop.obs.health, self.real, self.config.cost.contact_threshold
        feels = (torch.linalg.vector_norm(real.force, dim=-1) > threshold).any(-1) | (real.touch > threshold).any(-1)
        holds = feels | ((real.has_touch < 0.5) & ((real.has_force < 0.5) | self.pop.layout.carries_on_palm))  # (G,)
        return (health != HEALTH_OK) & ((health != HEALTH_AWAY) | holds[:, None]), feels

    def weights(self) -> torch.Tensor:
        """Each world's share of the estimate now, (G, K), from the window's cost (uniform after an update)."""
        return estimate_pmf(torch.nan_to_num(self.scored(), nan=0.0), self.config.estimate.estimate_lambda)

    def scored(self) -> torch.Tensor:
        """The window's mean cost per world with the pose observations' evidence added, (G, K).
        The evidence is scaled by the spread of the contact costs of the worlds that still hold
        the object (a lost world's 1e9 would swamp it): the optimizers rank by cost relative to its
        spread, so an observation weighs the same whatever the cost's units; where the contact
        costs do not separate the worlds (before the grasp), it weighs as the optimizers' least
        meaningful spread, and the observation decides."""
        window, top, bottom = self.windows.means()
        # At least the spread below which the optimizers see only noise and skip the update: where
        # contact does not separate the worlds (before the grasp, or with the object left on the
        # table) the observation alone must be able to move them.
        spread = torch.nan_to_num(top - bottom, nan=0.0, posinf=0.0, neginf=0.0)
        return window + self.windows.evidence * spread.clamp_min(self.config.optimizer.min_spread)

    def _summary(self, window: torch.Tensor, lost: torch.Tensor, feels: torch.Tensor) -> torch.Tensor:
        """Everything the estimate needs, packed by :data:`.layout.ESTIMATE` for one device->host copy;
        ``lost`` (G, K): the worlds that lost their object; ``feels`` (G,): the robot feels it."""
        pop, olp, cfg = self.pop, self.olp[:, None], self.config
        # An OLP group reports its first world: on a GPU its identical worlds can drift apart by float
        # atomics, and their mean would be an ensemble, not the one dead-reckoned world OLP stands for.
        anchor, sharp = torch.where(olp, self._first, self._anchor), self._sharpness.masked_fill(olp, 0.0)
        reckon = open_loop_share(self._reckoned, window, self._anchor, feels, cfg.optimizer)
        best, poses = pose_statistics(pop.obs.object_pose, window, self._origin, cfg.estimate, sharp, anchor, reckon)
        at_best = lambda t: t.gather(1, best[:, None])[:, 0]  # noqa: E731
        self.residuals.add(self.cost.last_terms, best)
        return ESTIMATE.pack(
            {
                **poses,
                "cost": at_best(window),
                "mass": at_best(pop.mass),
                "friction": at_best(pop.friction),
                "lost": lost.float().mean(-1),
                "contact_disagreement": at_best(self.cost.last_terms[..., 3]),  # sensors in disagreement
                "hand": self.real.sensor_pos.mean(1),
                "contacts_explored": self.contacts.open.float(),
                "overflow": pop.dropped().any(-1).float(),
                "separation": self._evidence[:, 0],
                "evidence": self._evidence[:, 1],
                "residual": self.residuals.mean,
            }
        )

    def _update_ops(self) -> None:
        """The captured update: the optimizer's resample and perturbation, as strong as the window's evidence for it."""
        cfg = self.config
        # Worlds apart from noise: the window's mean scatter against its means.
        separated = self.windows.separation(declared_scatter(self.cost, self.pop.robot_spec, self.L, self.pop.Z))
        self._evidence[:, 0].copy_(separated)
        cost = self.scored()
        scale, strength = self._exploration[:, None], None
        if cfg.optimizer.by_evidence:  # parameter noise, wrench and roughening as strong as the selection
            strength = evidence_strength(separated, self.windows.noise_bound(), cfg.optimizer.reps_epsilon)
            scale = scale * strength
        unfelt = self._reckoned[:, 2] < 0.5  # the robot has not felt the object since the group was seeded
        upd = update(cost, cfg.optimizer, self.gen, self.methods, self._rows, separated, strength, unfelt)
        explores = upd.explore.any(-1) & ~self.olp & (self._exploration > 0)
        opens = self.contacts.gate(self.windows.means()[2][:, 0], explores) if self.contacts.enabled else None
        servo_opens = self.servos.gate(self.joints.rms(), explores) if self.servos.enabled else None
        params, pose = torch.stack([self.pop.mass, self.pop.friction], dim=-1), self.pop.obs.object_pose
        state, posed, sharpness = pose_sources(upd.index, cost, pose, params, cfg.optimizer, strength, self.gen)
        pose_scale = scale if strength is None else self._exploration[:, None] * sharpness
        if strength is not None:  # what the update did to the poses, and so to the estimate
            self._evidence[:, 1:].copy_(sharpness)
        self._sharpness.copy_(sharpness)
        # The open-loop world keeps its own state, unperturbed, but under by_evidence for a full-strength update,
        # which restarts it from the best world: dead reckoning from the last sure estimate.
        restart = (sharpness >= 1.0) & upd.explore.any(-1, keepdim=True) & cfg.optimizer.by_evidence
        source = torch.where(restart, cost.argmin(-1, keepdim=True), 0)
        state, upd.index = torch.where(self._anchor, source, state), torch.where(self._anchor, source, upd.index)
        upd.explore = upd.explore & ~self._anchor
        self.pop.copy_worlds(state, upd.index)
        if not set(self.methods) <= {"OLP", "EYE"}:
            explore, ex, gen = upd.explore, cfg.exploration, self.gen
            mass = perturb_within(self.pop.mass, ex.mass_sigma * scale, self._mass_range, explore, gen)
            friction = perturb_within(self.pop.friction, ex.friction_sigma * scale, self._friction_range, explore, gen)
            contacts = () if opens is None else self.contacts.explored(explore, scale, opens)
            self.pop.write_params(mass, friction, *contacts)
            if servo_opens is not None:
                self.servos.explored(upd.index, explore, scale, servo_opens)
            wrench = sample_wrenches((self.G, self.K), ex.wrench_force, ex.wrench_torque, self.gen, self.device)
            # The wrench and the roughening explore the poses: only where the poses were resampled.
            self.pop.set_wrench(wrench * ((explore & posed)[..., None] * pose_scale[..., None]))
            keep = chance_shift(pose, cost < HELD_COST, state) if ex.undo_chance_shift and not ex.keep_mean else None
            self._move_copies(state, explore & posed, pose_scale, strength is not None, keep)
        self.windows.restart(upd.held_back, upd.index)

    def _move_copies(self, state, explore, scale, in_place: bool, keep: tuple | None = None) -> None:
        """Roughen the object poses of the resampled worlds' copies (of ``state`` (G, K), where
        ``explore``), then move them together to keep the estimate's mean (``keep_mean``), or ``keep``'s
        pose (G, 7) by its share (G, 6) per direction (``undo_chance_shift``). Only the copies move:
        each surviving world keeps one copy where it was, so the estimate does not jitter with it."""
        # In place a world that took another's state is a copy; else each source's first slot holds the original.
        copies = state != torch.arange(self.K, device=self.device) if in_place else duplicates(state)
        cfg, moved = self.config.exploration, explore & copies
        if cfg.jitter_t > 0 or cfg.jitter_r > 0 or self._bandwidth > 0:
            unit = torch.randn((self.G, self.K, 6), generator=self.gen, device=self.device)
            pose = self.pop.obs.object_pose.gather(1, state[..., None].expand(-1, -1, 7))  # resampled
            sigma = self._jitter_floor.expand(self.G, 1, 6)
            if self._bandwidth > 0:
                sigma = roughening_sigma(pose, self._bandwidth, self._jitter_floor, self._jitter_ceiling)
            shift = unit * sigma + (shrink_toward_mean(pose, self._shrink) if self._shrink > 0 else 0.0)
            self.pop.displace_object(shift * (moved[..., None] * scale[..., None]))
        if cfg.keep_mean:  # the frame before packed the estimate's mean over all worlds
            self.pop.displace_object(recentre(self.pop.object_coords, ESTIMATE.view(self._packed, "mean_pose"), moved))
        elif keep is not None:
            self.pop.displace_object(recentre(self.pop.object_coords, keep[0], moved, keep[1]))
