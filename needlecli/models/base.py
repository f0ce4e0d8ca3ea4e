"""The model contract.

A model knows its equations and nothing else: state and input names with units, which states are angles,
the vector field ``f(x, u, p)`` batched over any leading axes, its Jacobians, an RK4 step, the tip
quantities that sensors measure (position, rotation, tangent, roll, field direction), and a check of its
domain. Parameters are passed as a mapping ``name -> array`` broadcastable to the batch shape ``x.shape[:-1]``
so that they may differ between runs and change with time (tissue layers).

New models are added by subclassing :class:`Model` and decorating with ``@MODELS.register("name")``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from needlecli.models import MODELS  # noqa: F401  (the registry, at the package's front door)
from needlecli.numerics import complex_step_jacobian, rk4_step
from needlecli.schema import Strict

Params = Mapping[str, np.ndarray]


class StateSelection:
    """A measurement function that picks states: ``h(x) = x[..., index]``.

    Linear, so filters may use its closed form (``H P H^T`` is ``P[index][:, index]``) instead of
    propagating sigma points or Jacobians through it; the unscented transform of a linear ``h`` is that
    closed form exactly. Sensors return one from :meth:`~needlecli.sensors.Sensor.state_selection`.
    """

    __slots__ = ("index",)

    def __init__(self, index) -> None:
        self.index = np.asarray(index, dtype=np.int64)
        self.index.setflags(write=False)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return x[..., self.index]

    def __repr__(self) -> str:
        return f"StateSelection({self.index.tolist()})"


class ModelParams(Strict):
    """Base schema of a model's parameters in a config (``model.params``): strict and finite, as every
    config section (:class:`~needlecli.schema.Strict`)."""


class NotMeasurable(Exception):
    """Raised when a sensor asks a model for a quantity it does not have (e.g. position on SO(3))."""


class Model:
    """Base class of kinematic needle models.

    Class attributes
    ----------------
    state_names, state_units : tuple of str
    angle_states : tuple of str
        States compared and averaged wrapped.
    input_names, input_sizes, input_units : inputs in order; ``input_sizes[name]`` entries each
    insertion_input : str
        The input whose time integral is the inserted length (depth).
    curvature_param : str or None
        The parameter that tissue layers set as a function of depth.
    curvature_roll_state : str or None
        A roll angle such that ``(-curvature, roll + pi)`` gives the same path as ``(curvature, roll)``
        (the unicycle's ``gamma``): fits report a negative fitted curvature as that (None: no symmetry).
    length_unit : str
        Unit of positions (``mm``; ``m`` for the magnetic models of the magnetic needle EM paper).
    Params : pydantic schema of ``model.params`` in a config.
    """

    state_names: ClassVar[tuple[str, ...]] = ()
    state_units: ClassVar[tuple[str, ...]] = ()
    angle_states: ClassVar[tuple[str, ...]] = ()
    input_names: ClassVar[tuple[str, ...]] = ()
    input_sizes: ClassVar[dict[str, int]] = {}
    input_units: ClassVar[dict[str, str]] = {}
    insertion_input: ClassVar[str] = "v"
    curvature_param: ClassVar[str | None] = None
    curvature_roll_state: ClassVar[str | None] = None
    length_unit: ClassVar[str] = "mm"
    Params: ClassVar[type[ModelParams]] = ModelParams
    state_bounds: ClassVar[dict[str, tuple[float, float]]] = {}  # open intervals for initial states
    #: states the vector field does not depend on (the tip position of a kinematic model: its equations
    #: are invariant under translation); filters may propagate sigma points that differ only in these
    #: by the central point's displacement instead of through the model
    translation_states: ClassVar[tuple[str, ...]] = ()
    #: measured quantities (method names below) that are plain states, e.g. ``{"roll": ("gamma",)}``
    selections: ClassVar[dict[str, tuple[str, ...]]] = {}
    #: measured quantities (method names below) that are a block of states normalised to unit length, e.g.
    #: ``{"tangent": ("hx", "hy", "hz")}`` (the compiled linearisation of EM reads them)
    unit_vectors: ClassVar[dict[str, tuple[str, ...]]] = {}
    #: parameters the model carries as states, parameter -> state (:meth:`sync_params` writes them)
    param_states: ClassVar[dict[str, str]] = {}
    #: the compiled twin of the equations (the names of :data:`needlecli.kernels.models.MODEL_IDS`:
    #: ``unicycle``, ``modified_unicycle``, ``so3``, ``mnm``, ``binm``), or None: the numpy path only. A
    #: model that names one has those equations' states, inputs and parameters in their order (a subclass
    #: that changes only what sensors measure keeps its parent's)
    compiled_equations: ClassVar[str | None] = None
    #: the singularity as the compiled kernels check it (:meth:`singularity_margin`), or None (none):
    #: ``("cos", (s,))`` the cosine of state ``s``; ``("perpendicular", (h1, h2, h3, b1, b2, b3))`` the |cos|
    #: of the angle between two vectors of states, and a step across their perpendicularity (the sign of
    #: their dot product, :meth:`crossed_singularity`)
    compiled_margin: ClassVar[tuple[str, tuple[str, ...]] | None] = None
    registered_name: ClassVar[str] = ""

    def __init__(self, params: ModelParams | None = None) -> None:
        self.params = params if params is not None else self.Params()

    # ----------------------------------------------------------------- sizes and names
    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return sum(self.input_sizes[k] for k in self.input_names)

    def input_slice(self, name: str) -> slice:
        start = 0
        for k in self.input_names:
            if k == name:
                return slice(start, start + self.input_sizes[k])
            start += self.input_sizes[k]
        raise KeyError(name)

    @property
    def angle_mask(self) -> np.ndarray:
        return np.array([s in self.angle_states for s in self.state_names])

    def index(self, name: str) -> int:
        return self.state_names.index(name)

    def param_arrays(self) -> dict[str, np.ndarray]:
        """Parameters from the config as float arrays (scalars broadcast over the batch)."""
        return {k: np.asarray(v, dtype=float) for k, v in self.params.model_dump().items()}

    # ----------------------------------------------------------------- dynamics
    def f(self, x: np.ndarray, u: np.ndarray, p: Params) -> np.ndarray:
        """Vector field ``x' (..., n)`` for state ``x (..., n)`` and inputs ``u (..., m)``."""
        if self.component_major:
            return np.moveaxis(self.f_components(np.moveaxis(x, -1, 0), np.moveaxis(np.asarray(u), -1, 0), p), 0, -1)
        raise NotImplementedError

    def jacobian(self, x: np.ndarray, u: np.ndarray, p: Params) -> np.ndarray:
        """``df/dx`` of shape ``(..., n, n)`` (complex step unless a subclass is analytic)."""
        u = np.asarray(u)
        return complex_step_jacobian(lambda xx: self.f(xx, u[..., None, :], _expand(p)), x)

    def input_jacobian(self, x: np.ndarray, u: np.ndarray, p: Params) -> np.ndarray:
        """``df/du`` of shape ``(..., n, m)``."""
        x = np.asarray(x)
        return complex_step_jacobian(lambda uu: self.f(x[..., None, :], uu, _expand(p)), u)

    def param_jacobian(self, x: np.ndarray, u: np.ndarray, p: Params, name: str) -> np.ndarray:
        """``df/dp`` of shape ``(..., n)`` for the parameter ``name`` (complex step unless analytic)."""
        pc = {k: np.asarray(v) for k, v in p.items()}
        pc[name] = pc[name] + 1e-30j
        return self.f(np.asarray(x), np.asarray(u), pc).imag / 1e-30

    #: the model writes its equations once, component-major, in :meth:`f_components`; ``f`` and ``step``
    #: follow from it (RK4 then runs on contiguous ``(n, ...)`` blocks: no strided reads or writes)
    component_major: ClassVar[bool] = False

    def f_components(self, x: np.ndarray, u: np.ndarray, p: Params) -> np.ndarray:
        """The vector field component-major: ``x (n, ...)``, ``u (m, ...)`` -> ``x' (n, ...)``. Models with
        ``component_major = True`` define this instead of :meth:`f`."""
        raise NotImplementedError

    def step(self, x: np.ndarray, u: np.ndarray, p: Params, dt: float) -> np.ndarray:
        """Advance by ``dt`` with RK4, inputs and parameters held over the step."""
        if self.component_major:
            x, u = np.asarray(x), np.asarray(u)
            if x.ndim == 1:  # one state: 0-d components would be scalars, which f cannot write in place
                return self.step(x[None], u[None] if u.ndim == 1 else u, p, dt)[0]
            xc = np.ascontiguousarray(x.transpose((x.ndim - 1, *range(x.ndim - 1))))
            uc = u.transpose((u.ndim - 1, *range(u.ndim - 1)))
            xn = rk4_step(lambda z: self.f_components(z, uc, p), xc, dt)
            return self.normalize(np.ascontiguousarray(xn.transpose((*range(1, xn.ndim), 0))))
        return self.normalize(rk4_step(lambda xx: self.f(xx, u, p), x, dt))

    def normalize(self, x: np.ndarray) -> np.ndarray:
        """Bring a state back onto its manifold after a step (identity by default)."""
        return x

    def sync_params(self, x: np.ndarray, p: Params) -> np.ndarray:
        """Write the parameters that the model carries as states (:attr:`param_states`, e.g. the
        curvature) into a copy of ``x``; ``x`` itself where there are none."""
        if not self.param_states:
            return x
        x = x.copy()
        for name, state in self.param_states.items():
            x[..., self.index(state)] = p[name]
        return x

    def initial_state(self, p: Params) -> np.ndarray:
        """Default initial state ``(n,)``: at the origin, pointing along +z."""
        raise NotImplementedError

    # ----------------------------------------------------------------- domain
    #: below ``singular_threshold`` the state is outside the domain; a blow-up of a state whose margin
    #: is below ``near_singular_threshold`` is attributed to the singularity rather than to divergence.
    singular_threshold: ClassVar[float] = 0.0
    near_singular_threshold: ClassVar[float] = 0.0
    singular_reason: ClassVar[str] = ""

    def singularity_margin(self, x: np.ndarray, p: Params) -> np.ndarray | None:
        """Distance ``(...)`` to the model's singularity (None when it has none)."""
        return None

    def singular(self, x: np.ndarray, p: Params) -> np.ndarray:
        """Boolean ``(...)``: True where the state left the model's domain (NaN counts as outside)."""
        m = self.singularity_margin(x, p)
        if m is None:
            return np.zeros(np.shape(x)[:-1], dtype=bool)
        return ~(m > self.singular_threshold)

    def near_singular(self, x: np.ndarray, p: Params) -> np.ndarray:
        m = self.singularity_margin(x, p)
        if m is None:
            return np.zeros(np.shape(x)[:-1], dtype=bool)
        return ~(m > self.near_singular_threshold)

    def crossed_singularity(self, x: np.ndarray, xn: np.ndarray, p: Params) -> np.ndarray:
        """Boolean ``(...)``: True where one step from ``x`` to ``xn`` jumped over the singularity without
        a grid time inside the singular band. Never, unless a model says how to tell."""
        return np.zeros(np.shape(xn)[:-1], dtype=bool)

    def left_domain(self, x: np.ndarray, xn: np.ndarray, p: Params) -> np.ndarray:
        """Whether the step ``x -> xn`` ended in, or jumped over, the singularity (what runs check)."""
        return self.singular(xn, p) | self.crossed_singularity(x, xn, p)

    # ----------------------------------------------------------------- what sensors measure
    def tip_position(self, x: np.ndarray) -> np.ndarray:
        raise NotMeasurable(f"model {self.registered_name!r} has no tip position")

    def tip_rotation(self, x: np.ndarray) -> np.ndarray:
        raise NotMeasurable(f"model {self.registered_name!r} has no tip orientation")

    def tangent(self, x: np.ndarray) -> np.ndarray:
        return self.tip_rotation(x)[..., :, 2]

    def roll(self, x: np.ndarray) -> np.ndarray:
        raise NotMeasurable(f"model {self.registered_name!r} has no roll angle")

    def field_direction(self, x: np.ndarray) -> np.ndarray:
        raise NotMeasurable(f"model {self.registered_name!r} has no magnetic field state")

    def state_selection(self, quantity: str) -> np.ndarray | None:
        """Indices of the states that ``quantity`` (e.g. ``"tip_position"``) returns unchanged, or None
        where it is a nonlinear function of the state."""
        names = self.selections.get(quantity)
        return None if names is None else np.array([self.index(k) for k in names], dtype=np.int64)

    @classmethod
    def provides(cls, quantity: str) -> bool:
        """Whether the model defines ``quantity`` (a method name above)."""
        return getattr(cls, quantity) is not getattr(Model, quantity) or (
            quantity == "tangent" and cls.provides("tip_rotation")
        )


def _expand(p: Params) -> dict[str, np.ndarray]:
    """Add a perturbation axis to per-batch parameters for the complex-step Jacobian."""
    return {k: np.asarray(v)[..., None] if np.ndim(v) else v for k, v in p.items()}


def state_blocks(names, skip=()) -> dict[str, list[int]]:
    """State indices grouped by their stem (``px, py, pz -> p``; ``hx, hy, hz -> h``; a name of one
    letter is its own block), the names in ``skip`` (e.g. augmented constants) left out: the blocks whose
    process noise the magnetic needle EM paper's tables report (``tr(Q_p)``, ...)."""
    out: dict[str, list[int]] = {}
    for i, s in enumerate(names):
        if s in skip:
            continue
        stem = s[:-1] if len(s) > 1 and s[-1] in "xyz" else s
        out.setdefault(stem, []).append(i)
    return out
