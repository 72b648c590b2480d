"""``load_robot`` and ``Robot``: a compiled MuJoCo model with its dynamics in JAX.

The ``Robot`` methods validate their inputs (shape, NaN, names: ``InputError``) and call jitted
pure functions of ``jaxcomp.dynamics`` that close over the model's constants. Units: q in rad
(hinge) or m (slide), dq in rad/s or m/s, torques in N m or N, positions in m, world (base) frame.
"""

import hashlib
import weakref
from collections.abc import Callable, Hashable, Sequence
from functools import cached_property
from pathlib import Path
from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxcomp import checks, dynamics, poses
from jaxcomp.errors import InputError, ModelError
from jaxcomp.kinematic_tree import KinematicTree, tree_from_mujoco
from jaxcomp.models import BUILTIN
from jaxcomp.params import InertialParams, add_point_mass
from jaxcomp.reduction import Reduction, as_is, plan_reduction, reduce_spec

T = TypeVar("T")

#: Poses every robot has: keyframe name -> the ``Robot`` attribute used when the model lacks it.
DEFAULT_POSES = {
    "home": "start_pose",
    "preferred": "start_pose",
    "rest": "rest_pose",
    "zero": "zero_pose",
}


def builtin_models() -> list[str]:
    """Names accepted by ``load_robot`` besides file paths."""
    return sorted(BUILTIN)


def _compile(name_or_path: str | Path) -> tuple[str, Path, mujoco.MjModel]:
    key = str(name_or_path)
    if key in BUILTIN:
        path = BUILTIN[key]
        name = key
    else:
        path = Path(key).expanduser()
        if path.suffix.lower() not in (".xml", ".mjcf", ".urdf") and not path.exists():
            raise ModelError(
                f"unknown robot {key!r}: not a built-in model ({', '.join(builtin_models())}) "
                "and not a path to an MJCF (.xml) or URDF (.urdf) file"
            )
        if not path.is_file():
            raise ModelError(f"robot model file not found: {path}")
        name = path.stem
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:  # MuJoCo raises ValueError with its parser's message
        text = str(exc)
        if "mass and inertia of moving bodies" in text:
            where = text.splitlines()[-1].strip()
            raise ModelError(
                f"{path}: a joint moves no mass ({where}): give the bodies below every joint "
                "an inertial (mass > 0), or remove the joint"
            ) from None
        raise ModelError(f"MuJoCo cannot compile {path}: {exc}") from None
    return name, path.resolve(), model


def model_digest(model: mujoco.MjModel) -> str:
    """SHA-256 of a compiled model (MuJoCo's binary MJB): equal for equal models, different
    after any edit, whatever the name or file.

    Args:
        model: a compiled ``mujoco.MjModel``.

    Returns:
        The digest, 64 hex digits.
    """
    buffer = np.empty(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return hashlib.sha256(buffer.tobytes()).hexdigest()


#: The robots loaded and still in use, by (name, file, model digest): weak, so a robot nobody
#: holds is freed, and keyed on the compiled content, so an edited file gives a new robot.
_IN_USE: "weakref.WeakValueDictionary[tuple[str, str, str], Robot]" = weakref.WeakValueDictionary()


def _reduced_spec(path: Path, full: mujoco.MjModel, reduction: Reduction) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_file(str(path))
    if reduction.changes_model:
        reduce_spec(spec, full, reduction)
    return spec


def load_robot(
    name_or_path: "str | Path | Robot",
    *,
    joints: Sequence[str] | None = None,
    site: str | None = None,
) -> "Robot":
    """A ``Robot`` from a built-in name (``builtin_models()``) or an MJCF / URDF path.

    The robot is the model reduced to its current-controlled joints (``jaxcomp.reduction``):
    ``joints`` (names) when given, else the model's ``jaxcomp_joints`` custom text, else the
    hinge joints that no equality constraint couples; the other joints are welded at their
    held position.

    While a robot loaded from the same, unchanged model is still in use somewhere, that robot is
    returned, so what it keeps (``Robot.cached``: compiled functions, plans, simulators) serves
    every caller.

    Args:
        name_or_path: a built-in name, MJCF/URDF path or ``Robot`` (kept unless ``joints`` differ).
        joints: names of the joints to current-control; None: the model's.
        site: the end-effector site's name, used when the model names none.

    Returns:
        The ``Robot``.

    Raises:
        ModelError: an unknown name or file, a model MuJoCo cannot compile, bad joints or site.
    """
    if isinstance(name_or_path, Robot):
        if joints is not None and tuple(joints) != name_or_path.controlled_joints:
            return load_robot(name_or_path.source or name_or_path.name, joints=joints, site=site)
        return name_or_path
    name, path, full = _compile(name_or_path)
    reduction = plan_reduction(full, joints, site)
    model = full
    if reduction.changes_model:
        try:
            model = _reduced_spec(path, full, reduction).compile()
        except Exception as exc:  # MuJoCo's compiler message
            raise ModelError(f"MuJoCo cannot compile {path} reduced to its joints: {exc}") from None
    key = (name, str(path), model_digest(model))
    robot = _IN_USE.get(key)
    if robot is None:
        robot = Robot(model, name=name, source=path, reduction=reduction, full_model=full)
        robot.__dict__["digest"] = key[2]  # the cached property, already computed
        _IN_USE[key] = robot
    return robot


class Robot:
    """A robot model: MuJoCo model, kinematic tree, and jitted dynamics.

    Attributes:
        name: built-in name or file stem. source: the model file.
        model: the compiled ``mujoco.MjModel``, reduced to the current-controlled joints (and a
            mobile base's joints). tree: its ``KinematicTree``.
        reduction: how the model file became ``model`` (``jaxcomp.reduction.Reduction``).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        name: str = "robot",
        source: Path | None = None,
        reduction: Reduction | None = None,
        full_model: mujoco.MjModel | None = None,
    ):
        self.model = model
        self.name = name
        self.source = source
        self.reduction = reduction if reduction is not None else as_is(model)
        self._full_model = full_model if full_model is not None else model
        self.tree: KinematicTree = tree_from_mujoco(model)
        self._cache: dict[Hashable, Any] = {}

    def __repr__(self) -> str:
        return f"Robot({self.name!r}, joints={list(self.joint_names)})"

    @cached_property
    def digest(self) -> str:
        """SHA-256 of the compiled model (``model_digest``): identifies the model's content."""
        return model_digest(self.model)

    # ----------------------------------------------------------------- names and constants
    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.tree.joint_names

    @property
    def link_names(self) -> tuple[str, ...]:
        return self.tree.body_names

    @property
    def site_names(self) -> tuple[str, ...]:
        return self.tree.site_names

    @property
    def nv(self) -> int:
        """Number of joints (degrees of freedom)."""
        return self.tree.nv

    @property
    def joint_limits(self) -> np.ndarray:
        """(nv, 2) lower and upper joint position limits, rad or m (inf when unlimited)."""
        return self.tree.joint_range.copy()

    @cached_property
    def effort_limits(self) -> np.ndarray:
        """(nv,) actuator torque limits, N m or N (inf when the model sets none)."""
        limited = self.model.jnt_actfrclimited.astype(bool)
        return np.where(limited, np.abs(self.model.jnt_actfrcrange).max(axis=1), np.inf)

    @cached_property
    def default_gravity(self) -> np.ndarray:
        """The model's gravity vector (3,) m/s^2 in the world frame (MuJoCo's opt.gravity)."""
        return self.model.opt.gravity.copy()

    def nominal_params(self) -> InertialParams:
        """The model's inertial parameters as JAX arrays (a fresh pytree)."""
        n = self.tree.nominal
        return InertialParams(jnp.asarray(n.mass), jnp.asarray(n.com), jnp.asarray(n.inertia))

    def custom_numeric(self, name: str) -> np.ndarray | None:
        """A ``<custom><numeric>`` array of the model, or None when absent.

        Args:
            name: the numeric's name.

        Returns:
            A copy of its data (size,), or None.
        """
        i = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
        if i < 0:
            return None
        adr, size = self.model.numeric_adr[i], self.model.numeric_size[i]
        return self.model.numeric_data[adr : adr + size].copy()

    def custom_text(self, name: str) -> str | None:
        """A ``<custom><text>`` string of the model, or None when absent.

        Args:
            name: the text's name.

        Returns:
            Its text, or None.
        """
        i = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_TEXT, name)
        if i < 0:
            return None
        adr, size = self.model.text_adr[i], self.model.text_size[i]
        return bytes(self.model.text_data[adr : adr + size]).decode().rstrip("\x00")

    @cached_property
    def named_poses(self) -> dict[str, np.ndarray]:
        """Keyframes of the model by name: joint positions (nv,), rad or m."""
        poses = {}
        for k in range(self.model.nkey):
            name = mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_KEY, k) or f"key{k}"
            poses[name] = self.model.key_qpos[k].copy()
        return poses

    @cached_property
    def rest_pose(self) -> np.ndarray:
        """(nv,) rad or m: the model's ``qpos0`` moved inside the joint limits
        (``poses.rest_pose``); calibration starts here when the model has no "home" keyframe."""
        return poses.rest_pose(self)

    @cached_property
    def start_pose(self) -> np.ndarray:
        """(nv,) rad or m: the controller's start pose when the model has no "home" keyframe,
        chosen on the model away from singularities and limits (``poses.start_pose``)."""
        return poses.start_pose(self)

    @property
    def idle_pose(self) -> np.ndarray:
        """(nv,) rad or m where simulators and recordings start by default: the "home"
        keyframe when the model has one, else ``rest_pose``."""
        return self.pose("home") if "home" in self.named_poses else self.rest_pose.copy()

    def pose(self, name: str) -> np.ndarray:
        """Joint positions (nv,) of a named pose (MJCF keyframe), rad or m. Without such a
        keyframe, "home" and "preferred" (the nullspace posture) are ``start_pose``, "rest" is
        ``rest_pose`` and "zero" is all zeros moved inside the limits.

        Args:
            name: a keyframe's name, or "home", "preferred", "rest" or "zero".

        Returns:
            (nv,) rad or m, a copy.

        Raises:
            InputError: an unknown pose.
        """
        if name in self.named_poses:
            return self.named_poses[name].copy()
        if name in DEFAULT_POSES:
            value = getattr(self, DEFAULT_POSES[name])
            return np.array(value() if callable(value) else value, float)
        known = sorted(set(self.named_poses) | set(DEFAULT_POSES))
        raise InputError(f"unknown pose {name!r} for {self.name}; known: {', '.join(known)}")

    def zero_pose(self) -> np.ndarray:
        """(nv,) zeros moved inside the joint limits."""
        return poses.inside_limits(np.zeros(self.nv), self.joint_limits)

    @property
    def end_effector(self) -> str:
        """Name of the end-effector site (``jaxcomp.reduction``: custom text
        ``jaxcomp_end_effector``, else ``end_effector``, else ``--site``, else one added)."""
        return self.reduction.site

    @property
    def reference(self) -> str:
        """How files name this model (``model`` fields): the built-in name, else the file path."""
        if self.name in BUILTIN and self.source == BUILTIN[self.name].resolve():
            return self.name
        return str(self.source) if self.source is not None else self.name

    @property
    def controlled_joints(self) -> tuple[str, ...]:
        """Names of the current-controlled joints (model order)."""
        return self.reduction.controlled

    @property
    def held_joints(self) -> dict[str, float]:
        """Joints of the model file welded at their held position: {name: rad or m}."""
        return dict(self.reduction.held)

    def spec(self) -> mujoco.MjSpec:
        """A fresh ``MjSpec`` of this robot's (reduced) model, for simulators to build on."""
        if self.source is None:
            raise ModelError(f"{self.name} was not loaded from a model file")
        return _reduced_spec(self.source, self._full_model, self.reduction)

    def _per_joint(self, name: str, values: list) -> list | None:
        """``values`` of a per-joint custom field mapped onto the current-controlled joints:
        listed for the joints the model declares (``Reduction.declared``) or for every joint of
        the model file; None where a joint has no value."""
        for listed in (self.reduction.declared, self._file_joints):
            if len(values) == len(listed):
                given = dict(zip(listed, values, strict=True))
                return [given.get(j) for j in self.controlled_joints]
        raise ModelError(
            f"{self.name}: custom field {name} has {len(values)} entries; it needs one per "
            f"current-controlled joint ({', '.join(self.reduction.declared)})"
        )

    @cached_property
    def _file_joints(self) -> tuple[str, ...]:
        m = self._full_model
        return tuple(
            mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}" for j in range(m.njnt)
        )

    def joint_numeric(self, name: str) -> np.ndarray | None:
        """A per-joint ``<custom><numeric>`` for the current-controlled joints (n,) (NaN for a
        joint it gives no value), or None when absent. A single value applies to every joint.

        Args:
            name: the numeric's name.

        Returns:
            (n,) floats, or None.

        Raises:
            ModelError: its entries fit neither the declared joints nor the file's.
        """
        data = self.custom_numeric(name)
        if data is None:
            return None
        if data.size == 1:
            return np.full(len(self.controlled_joints), float(data[0]))
        values = self._per_joint(name, data.tolist())
        return np.array([np.nan if v is None else v for v in values], float)

    @property
    def actuator_types(self) -> tuple[str, ...] | None:
        """Actuator type label of each current-controlled joint (custom text
        ``jaxcomp_actuator_types``, whitespace-separated; a joint it lists no type for is its
        own type), or None when the model has none."""
        text = self.custom_text("jaxcomp_actuator_types")
        if not text:
            return None
        types = self._per_joint("jaxcomp_actuator_types", text.split())
        return tuple(t or f"joint:{j}" for t, j in zip(types, self.controlled_joints, strict=True))

    def with_payload(self, params: InertialParams, mass, com) -> InertialParams:
        """``params`` plus a point payload of ``mass`` kg at ``com`` (3,) m in the
        end-effector site's frame, merged into the site's link.

        Args:
            params: the link inertials (link frames).
            mass: the payload's mass, kg.
            com: (3,) m, its centre of mass in the end-effector site's frame.

        Returns:
            ``params`` with the site link's mass, COM and inertia replaced (``add_point_mass``).
        """
        s = self.site_index(self.end_effector)
        point = self.tree.site_pos[s] + self.tree.site_rot[s] @ jnp.asarray(com)
        return add_point_mass(params, int(self.tree.site_body[s]), mass, point)

    def link_index(self, link: str) -> int:
        """Index of a link (body) by name.

        Args:
            link: the link's name.

        Returns:
            Its index into ``link_names`` and the params' arrays.

        Raises:
            InputError: an unknown link.
        """
        try:
            return self.tree.body_names.index(link)
        except ValueError:
            raise InputError(
                f"unknown link {link!r} for {self.name}; links: {', '.join(self.link_names)}"
            ) from None

    def site_index(self, site: str) -> int:
        """Index of a site by name.

        Args:
            site: the site's name.

        Returns:
            Its index into ``site_names``.

        Raises:
            InputError: an unknown site.
        """
        try:
            return self.tree.site_names.index(site)
        except ValueError:
            known = ", ".join(self.site_names) or "none"
            raise InputError(f"unknown site {site!r} for {self.name}; sites: {known}") from None

    # ----------------------------------------------------------------- input checks
    def check_q(self, q, what: str = "q") -> jax.Array:
        """q as a float array of shape (nv,), or InputError naming the problem.

        Args:
            q: (nv,) rad or m (velocities: rad/s or m/s); a tracer: its shape only.
            what: its name in messages.

        Returns:
            (nv,) JAX array.

        Raises:
            InputError: not numbers, a shape other than (nv,), or NaN or inf.
        """
        if not isinstance(q, jax.core.Tracer):
            q = checks.array(
                q, what, n=self.nv, labels=self.joint_names, kind="joint(s)", unit="rad or m"
            )
        elif q.shape != (self.nv,):
            raise InputError(
                f"{what} must have shape ({self.nv},) in rad or m for joint(s) "
                f"{', '.join(self.joint_names)}, got shape {tuple(q.shape)}"
            )
        return jnp.asarray(q)

    @cached_property
    def _device_defaults(self) -> tuple[InertialParams, jax.Array]:
        """Nominal params and default gravity placed on the device once, not on every call."""
        return self.nominal_params(), jnp.asarray(self.default_gravity)

    def check_gravity(self, gravity) -> jax.Array:
        """``gravity`` as a JAX array (3,), or the model's default gravity for None.

        Args:
            gravity: (3,) m/s^2 in the world (base) frame, or None.

        Returns:
            (3,) m/s^2.

        Raises:
            InputError: not a finite vector of shape (3,).
        """
        if gravity is None:
            return self._device_defaults[1]
        return jnp.asarray(checks.array(gravity, "gravity", n=3, unit="m/s^2"))

    def check_params(self, params: InertialParams | None) -> InertialParams:
        """``params`` (None: the nominal ones) or InputError: each field of its shape, finite,
        no negative link mass (values are checked unless traced, e.g. under ``jax.grad``).

        Args:
            params: mass (nb,) kg, com (nb, 3) m, inertia (nb, 3, 3) kg m^2 (link frames).

        Returns:
            ``params`` itself, or the nominal params.

        Raises:
            InputError: a wrong shape, NaN or inf, or a negative mass.
        """
        if params is None:
            return self._device_defaults[0]
        nb = self.tree.nb
        shapes = {"mass": (nb,), "com": (nb, 3), "inertia": (nb, 3, 3)}
        units = {"mass": "kg", "com": "m", "inertia": "kg m^2"}
        for field, shape in shapes.items():
            value = getattr(params, field)
            if tuple(np.shape(value)) != shape:
                raise InputError(
                    f"params.{field} must have shape {shape}, got {tuple(np.shape(value))}"
                )
            if isinstance(value, jax.core.Tracer):
                continue
            checks.array(
                value,
                f"params.{field}",
                shape=shape,
                labels=self.link_names,
                unit=units[field],
                nonneg=field == "mass",
            )
        return params

    # ----------------------------------------------------------------- dynamics
    def cached(self, key: Hashable, build: Callable[[], T]) -> T:
        """``build()``, made once per robot and key and kept on the robot (no global caches).

        For anything derived from this robot's model alone: compiled functions, plans, gains.

        Args:
            key: what names the value among the robot's.
            build: makes the value (called once).

        Returns:
            The value.
        """
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    def _fn(self, key: str, build: Callable[[], Callable]) -> Callable:
        return self.cached(("jit", key), lambda: jax.jit(build()))

    def forward_kinematics(self, q) -> dynamics.Frames:
        """World frames of all links and joints (see ``dynamics.Frames``).

        Args:
            q: joint positions (nv,), rad (slides: m).

        Returns:
            ``dynamics.Frames`` of the links and joints, world frame.
        """
        return self._fn("fk", lambda: lambda q: dynamics.forward_kinematics(self.tree, q))(
            self.check_q(q)
        )

    def gravity(self, q, params: InertialParams | None = None, gravity=None) -> jax.Array:
        """g(q) (nv,) N m: joint torques holding the arm against gravity (m/s^2, base frame).

        Args:
            q: joint positions (nv,), rad (slides: m).
            params: link inertials, link frames (``check_params``); default the nominal.
            gravity: (3,) m/s^2, world (base) frame; default ``default_gravity``.

        Returns:
            g(q) (nv,), N m (N for a slide).
        """
        fn = self._fn("gravity", lambda: lambda q, p, g: dynamics.gravity(self.tree, q, p, g))
        return fn(self.check_q(q), self.check_params(params), self.check_gravity(gravity))

    def mass_matrix(self, q, params: InertialParams | None = None) -> jax.Array:
        """M(q) (nv, nv), kg m^2 (armature included).

        Args:
            q: joint positions (nv,), rad (slides: m).
            params: link inertials, link frames (``check_params``); default the nominal.

        Returns:
            M(q) (nv, nv): kg m^2 between hinges, kg between slides, kg m across.
        """
        fn = self._fn("mass", lambda: lambda q, p: dynamics.mass_matrix(self.tree, q, p))
        return fn(self.check_q(q), self.check_params(params))

    def coriolis(self, q, dq, params: InertialParams | None = None) -> jax.Array:
        """C(q, dq) dq (nv,), N m.

        Args:
            q, dq: joint positions (nv,) rad and velocities (nv,) rad/s (slides: m, m/s).
            params: link inertials, link frames (``check_params``); default the nominal.

        Returns:
            C(q, dq) dq (nv,), N m (N for a slide).
        """
        fn = self._fn("cor", lambda: lambda q, v, p: dynamics.coriolis(self.tree, q, v, p))
        return fn(self.check_q(q), self.check_q(dq, "dq"), self.check_params(params))

    def bias(self, q, dq, params: InertialParams | None = None, gravity=None) -> jax.Array:
        """C(q, dq) dq + g(q) (nv,), N m.

        Args:
            q, dq: joint positions (nv,) rad and velocities (nv,) rad/s (slides: m, m/s).
            params: link inertials, link frames (``check_params``); default the nominal.
            gravity: (3,) m/s^2, world (base) frame; default ``default_gravity``.

        Returns:
            C(q, dq) dq + g(q) (nv,), N m (N for a slide).
        """
        fn = self._fn("bias", lambda: lambda q, v, p, g: dynamics.bias(self.tree, q, v, p, g))
        return fn(
            self.check_q(q),
            self.check_q(dq, "dq"),
            self.check_params(params),
            self.check_gravity(gravity),
        )

    def _site_fn(self, kind: str, site: str, impl: Callable) -> Callable:
        s = self.site_index(site)
        return self._fn(f"{kind}:{site}", lambda: lambda *args: impl(self.tree, *args, s))

    def jacobian(self, q, site: str) -> jax.Array:
        """(6, nv) site Jacobian, world-aligned rows (vx, vy, vz, wx, wy, wz).

        Args:
            q, site: joint positions (nv,) rad (slides: m), and the site's name.

        Returns:
            (6, nv): linear rows m/rad (1 for a slide), angular rad/rad (0 for a slide).
        """
        return self._site_fn("jac", site, dynamics.site_jacobian)(self.check_q(q))

    def site_position(self, q, site: str) -> jax.Array:
        """(3,) world position of a site, m.

        Args:
            q, site: joint positions (nv,) rad (slides: m), and the site's name.

        Returns:
            (3,) m, world frame.
        """
        return self._site_fn("pose", site, dynamics.site_pose)(self.check_q(q))[0]

    def site_pose(self, q, site: str) -> tuple[jax.Array, jax.Array]:
        """World position (3,) m and rotation matrix (3, 3) of a site.

        Args:
            q, site: joint positions (nv,) rad (slides: m), and the site's name.

        Returns:
            (position (3,) m, rotation (3, 3): columns are the site's axes), world frame.
        """
        return self._site_fn("pose", site, dynamics.site_pose)(self.check_q(q))

    def subtree_com(self, q, params: InertialParams | None = None):
        """Centre of mass (nb, 3) m and mass (nb,) kg of every link's subtree.

        Args:
            q: joint positions (nv,), rad (slides: m).
            params: link inertials, link frames (``check_params``); default the nominal.

        Returns:
            (centre of mass (nb, 3) m in the world frame, mass (nb,) kg).
        """
        fn = self._fn("subcom", lambda: lambda q, p: dynamics.subtree_com(self.tree, q, p))
        return fn(self.check_q(q), self.check_params(params))

    def operational_space(
        self, q, dq, site: str, params: InertialParams | None = None
    ) -> dynamics.OperationalSpace:
        """Lambda, mu, J_bar and nullspace projector N of a site's position task.

        Args:
            q, dq: joint positions (nv,) rad and velocities (nv,) rad/s (slides: m, m/s).
            site: the site's name.
            params: link inertials, link frames (``check_params``); default the nominal.

        Returns:
            ``dynamics.OperationalSpace`` of the site's position, world frame.
        """
        s = self.site_index(site)
        fn = self._fn(
            f"os:{site}",
            lambda: lambda q, v, p: dynamics.operational_space(self.tree, q, v, s, p),
        )
        return fn(self.check_q(q), self.check_q(dq, "dq"), self.check_params(params))
