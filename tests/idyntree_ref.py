"""Independent, test-only reference for expected FT sensor wrenches, computed with iDynTree.

This module wraps iDynTree's ``ExtWrenchesAndJointTorquesEstimator.computeExpectedFTSensorsMeasurements``
so that our own (Pinocchio based) implementation can be checked against it. It is deliberately written
without reusing any code of the project.

Conventions verified by ``tests/test_idyntree_ref.py`` (iDynTree 15.1.0, iCubGenova09 and ergoCubSN001)
---------------------------------------------------------------------------------------------------------
* Output layout: ``[fx, fy, fz, tx, ty, tz]`` (force first, then torque), N and Nm.
* Frame: the reading is expressed in the *sensor frame* = frame of the child link of the FT fixed joint
  (which for these URDFs coincides with the joint frame) composed with the ``<origin>`` of the top-level
  ``<sensor type="force_torque">`` tag.  The moment is taken about the sensor frame origin.  For the
  iCub 3 / ergoCub URDFs the links ``<name>`` (e.g. ``l_leg_ft``) hang at the same pose, but the tests
  compute the frame from the sensor tag, not from those helper links.
* Which link it acts on: iDynTree's ``getAppliedWrenchLink()`` is the *parent* link for
  ``child_to_parent`` (legs, arms: wrench exerted by the child side Q on the parent side P) and the *child*
  link for ``parent_to_child`` (feet: wrench exerted by the parent side P on the child side Q).  This
  matches docs/labels.md, "The physics: expected wrenches".
* Signs, checked with static poses (zero velocity and acceleration) and gravity ``g`` pointing down:
    - root_link fixed, l_leg_ft (child_to_parent): the force, rotated to the world frame, is
      ``(0, 0, -m_leg * g)`` with ``m_leg`` the summed URDF masses of the links below the sensor: the
      hanging leg *pulls the hip down*.  In the sensor frame itself fz is *positive* (~ +100 N on iCub 3)
      because the sensor z axis points down (rpy roll = pi).
    - root_link fixed, l_foot_front_ft / l_foot_rear_ft (parent_to_child): the world force is
      ``(0, 0, +m_part * g)``: the ankle *holds the foot part up*.
    - l_sole fixed, contact only on l_foot_front: l_foot_rear_ft reads ``+m(l_foot_rear) * g`` upwards
      (the massless l_sole frame adds nothing), expressed in l_sole with gravity ``(0, 0, -g)``.
* Dynamic case (random q, dq, ddq, tilted gravity, root_link clamped): all 8 readings equal the child
  subtree's Newton-Euler wrench (sum of m (a_c - g) and I alpha + omega x I omega, Pinocchio kinematics)
  to 1e-6 relative, forces and moments, on both robots.
* Under-determined contacts (several unknown 6D wrenches, e.g. both feet) are resolved by iDynTree with a
  least-squares / minimum-norm split; such labels are not physically exact (docs/labels.md).

iDynTree API notes (things that are easy to get wrong)
------------------------------------------------------
* ``ModelLoader.loadReducedModelFromFile(path, movable_joints)`` *lumps* every fixed joint that is not in
  the list, including the FT sensor joints, so **all FT sensors silently disappear**.  The FT sensors'
  parent joints (``SixAxisForceTorqueSensor.getParentJoint()``) must be added to the considered joints.
  We do that explicitly and check that every FT sensor of the full model survives in the estimator.
* SWIG overloads want ``str`` (not ``pathlib.Path``) and ``iDynTree.StringVector`` for lists of names.
* DOF order = order of the considered-joints list for the movable joints in practice, but we never rely on
  it: the mapping uses ``model.getJoint(model.getJointIndex(name)).getDOFsOffset()``.
* ``getFrameIndex`` / ``getLinkIndex`` print ``[ERROR]`` to stderr for unknown names; we check with
  ``isFrameNameUsed`` first and raise ``ValueError`` listing the available names.
* Copying values in: ``setVal`` in a Python loop costs ~9 us for 32 joints, ``FromPython`` allocates.
  We instead wrap the C++ buffer (``data()`` pointer) once in a NumPy view (~0.2 us per copy).  The
  buffers are never resized, so the views stay valid; a self-check at construction falls back to
  ``setVal`` if the trick does not work.
* ``SensorsMeasurements.toVector`` stacks all FT sensors first (6 values each, in sensor index order),
  then the other sensor types (accelerometers, gyroscopes...); we read the first ``6 * n_ft`` values.
"""

from __future__ import annotations

import ctypes
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import idyntree.bindings as iDynTree
import numpy as np

__all__ = ["IDynTreeFT", "joint_limits", "movable_joints", "random_in_limits"]

_MOVABLE_TYPES = ("revolute", "continuous", "prismatic")


def _urdf_root(urdf_path: str | Path) -> ET.Element:
    path = Path(urdf_path)
    if not path.is_file():
        raise FileNotFoundError(f"URDF not found: {path}")
    return ET.parse(path).getroot()


def movable_joints(urdf_path: str | Path) -> list[str]:
    """All non-fixed joints (revolute, continuous, prismatic) of the URDF, in URDF file order.

    Only direct ``<joint>`` children of ``<robot>`` are considered (not ``<gazebo>`` or other extensions).
    """
    root = _urdf_root(urdf_path)
    return [j.get("name", "") for j in root.findall("joint") if j.get("type") in _MOVABLE_TYPES]


def joint_limits(urdf_path: str | Path, joint_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Position limits ``(lower, upper)`` of ``joint_names`` read from the URDF ``<limit>`` tags.

    ``continuous`` joints, or joints without ``lower``/``upper`` attributes, get ``[-pi, pi]``.
    Raises ValueError for unknown or non-movable joint names.
    """
    root = _urdf_root(urdf_path)
    by_name = {j.get("name"): j for j in root.findall("joint") if j.get("type") in _MOVABLE_TYPES}
    missing = [n for n in joint_names if n not in by_name]
    if missing:
        raise ValueError(
            f"Unknown or non-movable joints {missing}; available movable joints: {sorted(by_name)}"
        )
    lower = np.empty(len(joint_names))
    upper = np.empty(len(joint_names))
    for k, name in enumerate(joint_names):
        joint = by_name[name]
        limit = joint.find("limit")
        lo = limit.get("lower") if limit is not None else None
        hi = limit.get("upper") if limit is not None else None
        if joint.get("type") == "continuous" or lo is None or hi is None:
            lower[k], upper[k] = -math.pi, math.pi
        else:
            lower[k], upper[k] = float(lo), float(hi)
    return lower, upper


def random_in_limits(
    urdf_path: str | Path,
    joint_names: Sequence[str],
    n: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random joint states, each ``(n, len(joint_names))``, in the order of ``joint_names``.

    * q: uniform within each joint's URDF position limits (parsed with ``xml.etree``, see
      :func:`joint_limits`; ``continuous`` or unlimited joints use ``[-pi, pi]``), rad.
    * dq: uniform in ``[-1, 1]`` rad/s.
    * ddq: uniform in ``[-5, 5]`` rad/s^2.
    """
    lower, upper = joint_limits(urdf_path, joint_names)
    shape = (n, len(joint_names))
    q = rng.uniform(lower, upper, size=shape)
    dq = rng.uniform(-1.0, 1.0, size=shape)
    ddq = rng.uniform(-5.0, 5.0, size=shape)
    return q, dq, ddq


def _numpy_view(vec: Any, size: int) -> np.ndarray | None:
    """Zero-copy NumPy view of an iDynTree ``VectorDynSize``-like buffer, or None if unsupported.

    The returned view aliases C++ memory: it is valid as long as ``vec`` is alive and never resized.
    """
    try:
        addr = int(vec.data())
        view = np.ctypeslib.as_array((ctypes.c_double * size).from_address(addr))
    except Exception:  # noqa: BLE001 - any binding difference means "no view"
        return None
    # Self-check: a write through the view must be visible through the official API.
    probe = np.arange(1.0, size + 1.0)
    view[:] = probe
    ok = all(vec.getVal(k) == probe[k] for k in range(size))
    view[:] = 0.0
    return view if ok else None


class _Buffer:
    """An iDynTree vector plus the fastest available way to copy a NumPy row into it."""

    def __init__(self, vec: Any, size: int) -> None:
        self.vec = vec
        self.size = size
        self.view = _numpy_view(vec, size)

    def set(self, values: np.ndarray) -> None:
        if self.view is not None:
            self.view[:] = values
        else:
            setval = self.vec.setVal
            for k, v in enumerate(values.tolist()):
                setval(k, v)


class IDynTreeFT:
    """Expected FT sensor wrenches of a robot from iDynTree (reference implementation for tests).

    Parameters
    ----------
    urdf_path:
        URDF with ``<sensor type="force_torque">`` tags.
    joint_names:
        The movable joints, in the column order of the ``q, dq, ddq`` arrays given to :meth:`expected`.
        Defaults to :func:`movable_joints` (all non-fixed joints, URDF order).  Movable joints not listed
        are locked at 0 (iDynTree reduced model).

    Attributes
    ----------
    sensor_names:
        FT sensor names in iDynTree's sensor order (keys of the dict returned by :meth:`expected`).
    joint_names:
        The joint order of the inputs.
    """

    def __init__(self, urdf_path: str | Path, joint_names: Sequence[str] | None = None) -> None:
        path = Path(urdf_path)
        if not path.is_file():
            raise FileNotFoundError(f"URDF not found: {path}")
        self.urdf_path = path
        joint_names = movable_joints(path) if joint_names is None else list(joint_names)
        self.joint_names: list[str] = list(joint_names)
        if len(set(self.joint_names)) != len(self.joint_names):
            raise ValueError(f"Duplicated joint names in {self.joint_names}")

        # 1) Full model: find the FT sensors and their fixed joints, validate joint names.
        full_loader = iDynTree.ModelLoader()
        if not full_loader.loadModelFromFile(str(path)):
            raise RuntimeError(f"iDynTree could not load {path}")
        full_model = full_loader.model().copy()
        full_sensors = full_loader.sensors()
        n_ft_full = full_sensors.getNrOfSensors(iDynTree.SIX_AXIS_FORCE_TORQUE)
        full_ft = [full_sensors.getSixAxisForceTorqueSensor(k) for k in range(n_ft_full)]
        ft_names_full = [s.getName() for s in full_ft]
        ft_joints = [s.getParentJoint() for s in full_ft]

        movable_full = [
            full_model.getJointName(k)
            for k in range(full_model.getNrOfJoints())
            if full_model.getJoint(k).getNrOfDOFs() > 0
        ]
        bad = [n for n in self.joint_names if n not in movable_full]
        if bad:
            raise ValueError(
                f"Unknown or non-movable joints {bad}; available movable joints: {sorted(movable_full)}"
            )

        # 2) Reduced model: exactly joint_names as DOFs + the FT fixed joints (else FT sensors are lumped).
        considered = self.joint_names + [j for j in ft_joints if j not in self.joint_names]
        loader = iDynTree.ModelLoader()
        if not loader.loadReducedModelFromFullModel(full_model, iDynTree.StringVector(considered)):
            raise RuntimeError(f"iDynTree could not build the reduced model of {path}")
        model = loader.model()
        if model.getNrOfDOFs() != len(self.joint_names):
            raise RuntimeError(
                f"Reduced model has {model.getNrOfDOFs()} DOFs, expected {len(self.joint_names)}"
            )

        # 3) Estimator, built once.
        self._est = iDynTree.ExtWrenchesAndJointTorquesEstimator()
        if not self._est.setModelAndSensors(model, loader.sensors()):
            raise RuntimeError("ExtWrenchesAndJointTorquesEstimator.setModelAndSensors failed")
        self._model = self._est.model()
        sensors = self._est.sensors()
        self._n_ft = sensors.getNrOfSensors(iDynTree.SIX_AXIS_FORCE_TORQUE)
        self.sensor_names: list[str] = [
            sensors.getSensor(iDynTree.SIX_AXIS_FORCE_TORQUE, k).getName() for k in range(self._n_ft)
        ]
        if sorted(self.sensor_names) != sorted(ft_names_full):
            raise RuntimeError(
                f"FT sensors lost in the reduced model: full {ft_names_full}, estimator {self.sensor_names}"
            )

        # 4) Explicit mapping of our joint order -> iDynTree DOF order: idyn[k] = ours[self._to_idyn[k]].
        dof_of_ours = np.array(
            [self._model.getJoint(self._model.getJointIndex(n)).getDOFsOffset() for n in self.joint_names],
            dtype=int,
        )
        if sorted(dof_of_ours.tolist()) != list(range(len(self.joint_names))):
            raise RuntimeError(f"Unexpected iDynTree DOF offsets {dof_of_ours.tolist()}")
        self._to_idyn = np.argsort(dof_of_ours)

        # 5) All iDynTree buffers, allocated once.
        n = len(self.joint_names)
        self._q = _Buffer(iDynTree.JointPosDoubleArray(self._model), n)
        self._dq = _Buffer(iDynTree.JointDOFsDoubleArray(self._model), n)
        self._ddq = _Buffer(iDynTree.JointDOFsDoubleArray(self._model), n)
        self._gravity = _Buffer(iDynTree.Vector3(), 3)
        self._unknowns = iDynTree.LinkUnknownWrenchContacts(self._model)
        self._predicted = iDynTree.SensorsMeasurements(sensors)
        self._contact_wrenches = iDynTree.LinkContactWrenches(self._model)
        self._joint_torques = iDynTree.JointDOFsDoubleArray(self._model)
        self._wrench = iDynTree.Wrench()
        n_meas = self._predicted.getSizeOfAllSensorsMeasurements()
        self._meas_vec = iDynTree.VectorDynSize(n_meas)
        self._meas_view = _numpy_view(self._meas_vec, n_meas)
        if self._meas_view is not None:  # toVector must not reallocate, else the view would dangle
            addr = int(self._meas_vec.data())
            if not self._predicted.toVector(self._meas_vec) or int(self._meas_vec.data()) != addr:
                self._meas_view = None
        self._contacts: tuple[str, ...] | None = None

    # ------------------------------------------------------------------ names
    @property
    def frame_names(self) -> list[str]:
        """All frame names of the reduced model (links first, then additional frames)."""
        return [self._model.getFrameName(k) for k in range(self._model.getNrOfFrames())]

    @property
    def link_names(self) -> list[str]:
        """All link names of the reduced model."""
        return [self._model.getLinkName(k) for k in range(self._model.getNrOfLinks())]

    def frame_index(self, name: str) -> int:
        """iDynTree frame index of a link or additional frame; ValueError listing the names if unknown."""
        if not self._model.isFrameNameUsed(name):
            raise ValueError(f"Unknown frame/link {name!r}; available frames: {self.frame_names}")
        return self._model.getFrameIndex(name)

    # ------------------------------------------------------------- contacts
    def _set_contacts(self, contact_links: Sequence[str]) -> None:
        key = tuple(contact_links)
        if key == self._contacts:
            return
        if not key:
            raise ValueError("At least one contact link/frame is needed")
        indices = [self.frame_index(name) for name in key]  # validates all before modifying
        self._contacts = None
        self._unknowns.clear()
        for name, idx in zip(key, indices, strict=True):
            if not self._unknowns.addNewUnknownFullWrenchInFrameOrigin(self._model, idx):
                raise RuntimeError(f"addNewUnknownFullWrenchInFrameOrigin failed for {name!r}")
        self._contacts = key

    # ------------------------------------------------------------- main API
    def expected(
        self,
        q: np.ndarray,
        dq: np.ndarray,
        ddq: np.ndarray,
        contact_links: Sequence[str],
        fixed_frame: str,
        gravity_in_fixed_frame: np.ndarray,
    ) -> dict[str, np.ndarray]:
        """Expected FT measurements, as iDynTree's ``computeExpectedFTSensorsMeasurements`` defines them.

        Parameters
        ----------
        q, dq, ddq:
            ``(N, n_joints)`` (or ``(n_joints,)`` for one sample) in the order of ``joint_names``;
            rad, rad/s, rad/s^2.
        contact_links:
            Links or frames touching the environment; each gets one unknown full 6D wrench
            (``addNewUnknownFullWrenchInFrameOrigin``) on the link the frame belongs to.
        fixed_frame:
            Link or additional frame (e.g. ``l_sole``, ``root_link``) assumed fixed in an inertial frame.
        gravity_in_fixed_frame:
            Gravity acceleration (3,) expressed in ``fixed_frame``, e.g. ``(0, 0, -9.80665)``.

        Returns
        -------
        ``{sensor_name: (N, 6) [fx, fy, fz, tx, ty, tz]}`` in each sensor frame (see module docstring).
        """
        q2, dq2, ddq2 = (
            self._check_joint_array(a, label) for a, label in ((q, "q"), (dq, "dq"), (ddq, "ddq"))
        )
        n_samples = q2.shape[0]
        if dq2.shape[0] != n_samples or ddq2.shape[0] != n_samples:
            raise ValueError(
                f"q, dq, ddq must have the same number of rows: {q2.shape}, {dq2.shape}, {ddq2.shape}"
            )
        gravity = np.asarray(gravity_in_fixed_frame, dtype=float).reshape(-1)
        if gravity.shape != (3,):
            raise ValueError(f"gravity_in_fixed_frame must have 3 elements, got shape {gravity.shape}")
        fixed_index = self.frame_index(fixed_frame)
        self._set_contacts(contact_links)
        self._gravity.set(gravity)

        # Reorder once for the whole batch to iDynTree's DOF order, contiguous rows.
        qi = np.ascontiguousarray(q2[:, self._to_idyn])
        dqi = np.ascontiguousarray(dq2[:, self._to_idyn])
        ddqi = np.ascontiguousarray(ddq2[:, self._to_idyn])

        n_ft6 = 6 * self._n_ft
        out = np.empty((n_samples, n_ft6))
        est, pred = self._est, self._predicted
        q_buf, dq_buf, ddq_buf = self._q, self._dq, self._ddq
        qv, dqv, ddqv, gv = q_buf.vec, dq_buf.vec, ddq_buf.vec, self._gravity.vec
        unknowns, cw, tau = self._unknowns, self._contact_wrenches, self._joint_torques
        meas_vec, meas_view = self._meas_vec, self._meas_view
        for i in range(n_samples):
            q_buf.set(qi[i])
            dq_buf.set(dqi[i])
            ddq_buf.set(ddqi[i])
            if not est.updateKinematicsFromFixedBase(qv, dqv, ddqv, fixed_index, gv):
                raise RuntimeError(f"updateKinematicsFromFixedBase failed at sample {i}")
            if not est.computeExpectedFTSensorsMeasurements(unknowns, pred, cw, tau):
                raise RuntimeError(f"computeExpectedFTSensorsMeasurements failed at sample {i}")
            if meas_view is not None:
                pred.toVector(meas_vec)
                out[i] = meas_view[:n_ft6]
            else:
                self._read_slow(out[i])
        return {name: out[:, 6 * k : 6 * k + 6].copy() for k, name in enumerate(self.sensor_names)}

    def estimated_torques(
        self,
        q: np.ndarray,
        dq: np.ndarray,
        ddq: np.ndarray,
        contact_links: Sequence[str],
        fixed_frame: str,
        gravity_in_fixed_frame: np.ndarray,
        measured: dict[str, np.ndarray],
    ) -> np.ndarray:
        """``(N, n_joints)`` joint torques (Nm, ``joint_names`` order) from iDynTree's
        ``estimateExtWrenchesAndJointTorques``: the FT sensors' `measured` wrenches (sensor -> (N, 6), every
        sensor) split the robot into subtrees, each subtree's unknown contact wrenches (one full 6D wrench
        per link of `contact_links`) are estimated from its sensors, and the joint torques follow."""
        q2, dq2, ddq2 = (self._check_joint_array(a, n) for a, n in ((q, "q"), (dq, "dq"), (ddq, "ddq")))
        missing = sorted(set(self.sensor_names) - set(measured))
        if missing:
            raise ValueError(f"no measured wrench of {missing}")
        fixed_index = self.frame_index(fixed_frame)
        self._set_contacts(contact_links)
        self._gravity.set(np.asarray(gravity_in_fixed_frame, dtype=float).reshape(3))
        est, meas = self._est, iDynTree.SensorsMeasurements(self._est.sensors())
        out = np.empty(q2.shape)
        for i in range(q2.shape[0]):
            self._q.set(np.ascontiguousarray(q2[i, self._to_idyn]))
            self._dq.set(np.ascontiguousarray(dq2[i, self._to_idyn]))
            self._ddq.set(np.ascontiguousarray(ddq2[i, self._to_idyn]))
            if not est.updateKinematicsFromFixedBase(
                self._q.vec, self._dq.vec, self._ddq.vec, fixed_index, self._gravity.vec
            ):
                raise RuntimeError(f"updateKinematicsFromFixedBase failed at sample {i}")
            for k, name in enumerate(self.sensor_names):
                meas.setMeasurement(
                    iDynTree.SIX_AXIS_FORCE_TORQUE, k, iDynTree.Wrench.FromPython(measured[name][i])
                )
            if not est.estimateExtWrenchesAndJointTorques(
                self._unknowns, meas, self._contact_wrenches, self._joint_torques
            ):
                raise RuntimeError(f"estimateExtWrenchesAndJointTorques failed at sample {i}")
            out[i, self._to_idyn] = self._joint_torques.toNumPy()
        return out

    def sensor_poses(self, q: np.ndarray, frame: str, sensor: str) -> np.ndarray:
        """``(N, 4, 4)`` homogeneous pose of FT sensor `sensor`'s frame in link/frame `frame`.

        From iDynTree alone: ``KinDynComputations.getRelativeTransform(frame, link)`` for the link the
        sensor's wrench is applied to, composed with ``getLinkSensorTransform(link)`` of the sensor.
        q: ``(N, n_joints)`` in ``joint_names`` order, rad.
        """
        if not hasattr(self, "_kindyn"):
            self._kindyn = iDynTree.KinDynComputations()
            if not self._kindyn.loadRobotModel(self._model):
                raise RuntimeError("KinDynComputations.loadRobotModel failed")
        sensors = self._est.sensors()
        k = self.sensor_names.index(sensor)
        ft = sensors.getSixAxisForceTorqueSensor(k)
        link = ft.getAppliedWrenchLink()
        link_H_sensor = iDynTree.Transform()
        if not ft.getLinkSensorTransform(link, link_H_sensor):
            raise RuntimeError(f"getLinkSensorTransform failed for {sensor}")
        link_h = link_H_sensor.asHomogeneousTransform().toNumPy()
        frame_index = self.frame_index(frame)
        q2 = self._check_joint_array(q, "q")[:, self._to_idyn]
        out = np.empty((q2.shape[0], 4, 4))
        for i in range(q2.shape[0]):
            self._q.set(np.ascontiguousarray(q2[i]))
            self._kindyn.setJointPos(self._q.vec)
            rel = self._kindyn.getRelativeTransform(frame_index, link)
            out[i] = rel.asHomogeneousTransform().toNumPy() @ link_h
        return out

    def imu(
        self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, fixed: str, gravity: np.ndarray, sensor: str
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(N, 3)`` proper acceleration (m/s^2) and ``(N, 3)`` angular velocity (rad/s) of FT sensor
        `sensor`'s frame, in that frame, with link/frame `fixed` still in the world, whose gravity is
        `gravity` (3,) in `fixed`'s frame.

        From iDynTree alone: the sensor frame added to its link (`getLinkSensorTransform`), the floating
        base on `fixed`, ``getFrameVel`` / ``getFrameAcc`` in MIXED representation (the frame origin's
        classical acceleration and the angular velocity, world axes) rotated into the sensor frame.
        """
        kindyn = self._imu_model(sensor)
        kindyn.setFloatingBase(fixed if fixed in self.link_names else self._link_of(fixed))
        world_T_base = iDynTree.Transform.Identity()
        if fixed not in self.link_names:  # an additional frame (a sole): the world is that frame
            link_H_frame = self._model.getFrameTransform(self.frame_index(fixed))
            world_T_base = link_H_frame.inverse()
        g = iDynTree.Vector3.FromPython(np.asarray(gravity, dtype=float))
        zero6 = iDynTree.Twist.Zero()
        base_acc = iDynTree.Vector6.FromPython(np.zeros(6))
        frame = kindyn.getFrameIndex(f"{sensor}_imu_frame")
        arrays = [
            self._check_joint_array(a, n)[:, self._to_idyn] for a, n in ((q, "q"), (dq, "dq"), (ddq, "ddq"))
        ]
        acc, gyro = np.empty((len(arrays[0]), 3)), np.empty((len(arrays[0]), 3))
        s_q = iDynTree.VectorDynSize(len(self.joint_names))
        s_dq, s_ddq = (
            iDynTree.VectorDynSize(len(self.joint_names)),
            iDynTree.VectorDynSize(len(self.joint_names)),
        )
        for i in range(len(arrays[0])):
            for vec, a in zip((s_q, s_dq, s_ddq), arrays, strict=True):
                for k, v in enumerate(a[i]):
                    vec.setVal(k, float(v))
            kindyn.setRobotState(world_T_base, s_q, zero6, s_dq, g)
            rotation = kindyn.getWorldTransform(frame).getRotation().toNumPy()
            twist = kindyn.getFrameVel(frame).toNumPy()
            spatial = kindyn.getFrameAcc(frame, base_acc, s_ddq).toNumPy()
            acc[i] = rotation.T @ (spatial[:3] - np.asarray(gravity))
            gyro[i] = rotation.T @ twist[3:]
        return acc, gyro

    def _link_of(self, frame: str) -> str:
        return self._model.getLinkName(self._model.getFrameLink(self.frame_index(frame)))

    def _imu_model(self, sensor: str) -> Any:
        """A KinDynComputations of the model with the sensor's frame added to its link (MIXED)."""
        cache = self.__dict__.setdefault("_imu_kindyn", {})
        if sensor not in cache:
            ft = self._est.sensors().getSixAxisForceTorqueSensor(self.sensor_names.index(sensor))
            link = ft.getAppliedWrenchLink()
            link_H_sensor = iDynTree.Transform()
            if not ft.getLinkSensorTransform(link, link_H_sensor):
                raise RuntimeError(f"getLinkSensorTransform failed for {sensor}")
            model = self._model.copy()
            if not model.addAdditionalFrameToLink(
                model.getLinkName(link), f"{sensor}_imu_frame", link_H_sensor
            ):
                raise RuntimeError(f"cannot add the frame of {sensor}")
            kindyn = iDynTree.KinDynComputations()
            if not kindyn.loadRobotModel(model):
                raise RuntimeError("KinDynComputations.loadRobotModel failed")
            kindyn.setFrameVelocityRepresentation(iDynTree.MIXED_REPRESENTATION)
            cache[sensor] = kindyn
        return cache[sensor]

    def _read_slow(self, row: np.ndarray) -> None:
        for k in range(self._n_ft):
            self._predicted.getMeasurement(iDynTree.SIX_AXIS_FORCE_TORQUE, k, self._wrench)
            row[6 * k : 6 * k + 6] = self._wrench.toNumPy()

    def _check_joint_array(self, a: np.ndarray, label: str) -> np.ndarray:
        arr = np.asarray(a, dtype=float)
        if arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != len(self.joint_names):
            raise ValueError(
                f"{label} must be (N, {len(self.joint_names)}) in joint_names order, got {np.shape(a)}"
            )
        return arr
