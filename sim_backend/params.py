"""The physics parameters each world explores (the object's mass and friction, its contacts'
stiffness and friction impedance) as torch views of the model, and the solver's copies of the
inertial constants that follow the mass."""

from __future__ import annotations

import newton
import numpy as np
import torch
import warp as wp

from .build import BuiltModel, Physics

__all__ = ["ObjectParams"]


class ObjectParams:
    """Mass, friction and contact parameters of each world's object, shaped (G, K), written in
    place on the device.

    Public setters live on :class:`sim_backend.Population`, which checks the values; ``write`` is
    the unchecked writer the tracker's captured update uses.
    """

    def __init__(self, built: BuiltModel, physics: Physics, groups: int, worlds: int, device: torch.device):
        G, K, nb, o = groups, worlds, built.bodies, built.object_body
        model, t = built.model, wp.to_torch
        self.G, self.K = G, K
        self._solver = physics.solver
        self._nominal_mass = built.nominal_mass
        inertia = torch.tensor(built.nominal_inertia, dtype=torch.float32)
        # Kept on the device: the tracker's captured update writes the parameters, where a host
        # copy or a checked inverse would stall or break the capture.
        self._nominal_inertia = inertia.to(device)
        self._nominal_inv_inertia = torch.linalg.inv(inertia).to(device)
        self.mass = t(model.body_mass)[o::nb].view(G, K)
        """Object mass per world, (G, K) [kg]; a view of the model."""
        self._inv_mass = t(model.body_inv_mass)[o::nb].view(G, K)
        self._inertia = t(model.body_inertia)[o::nb].view(G, K, 3, 3)
        self._inv_inertia = t(model.body_inv_inertia)[o::nb].view(G, K, 3, 3)
        # The object's shapes sit at the same offset in every world: view them as (G, K, n).
        W = G * K
        shape_body = model.shape_body.numpy()
        obj_shapes = np.flatnonzero((shape_body >= 0) & (shape_body % nb == o)).reshape(W, -1)
        per_world = int(obj_shapes[1, 0] - obj_shapes[0, 0]) if W > 1 else 0
        expected = obj_shapes[0] + per_world * np.arange(W)[:, None]
        if not np.array_equal(obj_shapes, expected) or np.any(np.diff(obj_shapes[0]) != 1):
            raise ValueError("object shapes: expected the same contiguous shapes in every world")
        n = obj_shapes.shape[1]
        per_shape = lambda a: torch.as_strided(t(a), (G, K, n), (K * per_world, per_world, 1), int(obj_shapes[0, 0]))  # noqa: E731
        self._shape_mu = per_shape(model.shape_material_mu)
        self.friction = self._shape_mu[..., 0]
        """Object friction coefficient per world, (G, K); a view of the model."""
        # Contact softness: MuJoCo's solref from Newton's stiffness and damping (the object's
        # geoms take priority in its contacts with the hand, so its solref rules there).
        self._shape_ke, self._shape_kd = per_shape(model.shape_material_ke), per_shape(model.shape_material_kd)
        self._impratio_invsqrt = t(self._solver.mjw_model.opt.impratio_invsqrt).view(G, K)
        self.nominal_timeconst = float(self.timeconst[0, 0])
        self.nominal_impratio = float(self.impratio[0, 0])
        self.solver_constants = self._solver_views(built)
        """The solver's inertial constants of the object that its mass sets, by name, (G, K, ...)."""
        self._solver_nominal = {name: view.clone() for name, view in self.solver_constants.items()}

    def _solver_views(self, built: BuiltModel) -> dict[str, torch.Tensor]:
        """Views of the MuJoCo-Warp fields that the object's mass sets.

        Newton's notify_model_changed(BODY_INERTIAL_PROPERTIES) re-runs MuJoCo's set_const on every
        world (kinematics, composite inertia, a factorisation: 8.5 ms at K=40 on an H100, inside the
        update every T frames). The object is a free body whose inertia scales with its mass, so
        every constant it changes scales exactly: mass, principal inertia and subtree mass by s =
        m / m0, the inverse weights of the body and its six DOFs by 1 / s, the world's subtree mass
        by m - m0. Writing those directly gives set_const's values to float rounding (checked in
        tests/test_population.py) in a handful of torch ops."""
        G, K, t, mjm = self.G, self.K, wp.to_torch, self._solver.mjw_model
        body = int(np.flatnonzero(self._solver.mjc_body_to_newton.numpy()[0] == built.object_body)[0])
        dofs = np.flatnonzero(mjm.dof_bodyid.numpy() == body)
        if len(dofs) != 6 or np.any(np.diff(dofs) != 1):
            raise ValueError(f"object body: expected 6 contiguous solver DOFs, got {dofs.tolist()}")
        return {
            "mass": t(mjm.body_mass).view(G, K, -1)[..., body],
            "inertia": t(mjm.body_inertia).view(G, K, -1, 3)[..., body, :],
            "subtree": t(mjm.body_subtreemass).view(G, K, -1)[..., body],
            "root_subtree": t(mjm.body_subtreemass).view(G, K, -1)[..., 0],
            "invweight": t(mjm.body_invweight0).view(G, K, -1, 2)[..., body, :],
            "dof_invweight": t(mjm.dof_invweight0).view(G, K, -1)[..., dofs[0] : dofs[-1] + 1],
        }

    @property
    def timeconst(self) -> torch.Tensor:
        """Time constant of the object's contacts per world, (G, K) [s] (MuJoCo's solref, damping
        ratio 1): larger is softer."""
        return 2.0 / self._shape_kd[..., 0]

    @property
    def impratio(self) -> torch.Tensor:
        """Ratio of frictional to normal contact impedance per world, (G, K): how stiffly contacts
        resist sliding (MuJoCo's impratio)."""
        return self._impratio_invsqrt.pow(-2)

    @property
    def tensors(self) -> list[torch.Tensor]:
        """Every parameter tensor a resample copies, each (G, K, n)."""
        return [self.mass[..., None], self._inv_mass[..., None], self._shape_mu, self._shape_ke, self._shape_kd,
                self._impratio_invsqrt[..., None],
                self._inertia.view(self.G, self.K, 9), self._inv_inertia.view(self.G, self.K, 9)]  # fmt: skip

    def write_contacts(self, timeconst: torch.Tensor | None, impratio: torch.Tensor | None) -> None:
        """Set the contacts' time constant [s] and impratio, (G, K) on the device, unchecked and
        capture-safe as :meth:`write`. Call :meth:`notify` after."""
        if timeconst is not None:
            # Newton's (ke, kd) for MuJoCo's solref (timeconst, damping ratio 1): kd = 2 / timeconst,
            # ke = 1 / timeconst^2 (newton's convert_solref inverted).
            self._shape_kd.copy_((2.0 / timeconst)[..., None].expand_as(self._shape_kd))
            self._shape_ke.copy_(timeconst.pow(-2)[..., None].expand_as(self._shape_ke))
        if impratio is not None:
            self._impratio_invsqrt.copy_(impratio.rsqrt())

    def write(self, mass: torch.Tensor | None, friction: torch.Tensor | None) -> None:
        """Set mass [kg] (inertia scaled with it) and friction, (G, K) on the device, unchecked:
        no host work, so it can run inside a captured graph. Call :meth:`notify` after."""
        if mass is not None:
            scale = (mass / self._nominal_mass)[..., None, None]
            self.mass.copy_(mass)
            self._inv_mass.copy_(1.0 / mass)
            self._inertia.copy_(self._nominal_inertia * scale)
            self._inv_inertia.copy_(self._nominal_inv_inertia / scale)
            self.write_solver_constants()
        if friction is not None:
            self._shape_mu.copy_(friction[..., None].expand_as(self._shape_mu))

    def write_solver_constants(self) -> None:
        """The solver's copies of the object's inertial constants, from :attr:`mass`."""
        mj, mj0 = self.solver_constants, self._solver_nominal
        scale = self.mass / self._nominal_mass
        mj["mass"].copy_(self.mass)
        mj["subtree"].copy_(self.mass)
        mj["root_subtree"].copy_(mj0["root_subtree"] + (self.mass - self._nominal_mass))
        mj["inertia"].copy_(mj0["inertia"] * scale[..., None])
        mj["invweight"].copy_(mj0["invweight"] / scale[..., None])
        mj["dof_invweight"].copy_(mj0["dof_invweight"] / scale[..., None])

    def notify(self, device: wp.context.Device) -> None:
        """Push friction and contact softness to the solver. It also drops the solver's cached contact
        parameters, which a new mass makes stale too; the inertial constants themselves are written
        directly."""
        with wp.ScopedDevice(device):
            self._solver.notify_model_changed(newton.ModelFlags.SHAPE_PROPERTIES)
