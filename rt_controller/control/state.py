"""The compiled rule's state, declared once.

The per-tick rule (:mod:`~rt_controller.control.decide_kernel`) and the C/GMRES solver
(:mod:`~rt_controller.control.rhc`) keep all their state in flat float64 / int64 arrays, so
that a tick is one compiled call on preallocated memory. Each array's layout is declared here,
once, as an ordered list of :class:`Field`; everything else is generated from it:

* the offsets: a :class:`Block` is a namespace whose upper-case attributes are the offsets
  (``IO.TAU``, ``PAR.R_INV``, ``ST.U``), which numba reads as compile-time constants;
* the lengths (``IO.SIZE``), and the work array's cut (:data:`WORK`, :func:`work_offsets`);
* :class:`~rt_controller.control.controller.Decision`'s fields and the decision part of the
  cycle record and of its JSON Schema (the :data:`IO` fields with a ``record`` type).

Add a state variable by adding a :class:`Field` to its block (see CONTRIBUTING.md).
"""

from __future__ import annotations

import types
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rt_controller.control.model import NominalModel


@dataclass(frozen=True)
class Field:
    """One named slot of a block: ``size`` consecutive numbers."""

    name: str
    size: int = 1
    doc: str = ""
    record: str = ""
    """For :data:`IO` outputs in the cycle record: its JSON type, ``number``, ``integer``,
    ``boolean``, ``vector`` (2 numbers) or ``law`` (the mode, named); empty: not recorded."""


class Block(types.ModuleType):
    """An array layout: the fields in order, each at the offset after the previous one.

    A module object, because numba folds a module's integer attributes into the compiled code
    as constants (``io[IO.TAU + 1]`` costs what ``io[14]`` costs)."""

    def __init__(self, name: str, doc: str, fields: Sequence[Field]) -> None:
        super().__init__(f"{__name__}.{name}", doc)
        self.fields = tuple(fields)
        off = 0
        for f in self.fields:
            setattr(self, f.name.upper(), off)
            off += f.size
        self.SIZE = off

    def offset(self, name: str) -> int:
        """The offset of field ``name``."""
        return int(getattr(self, name.upper()))

    def field(self, name: str) -> Field:
        return next(f for f in self.fields if f.name == name)


def _fields(*spec: tuple) -> list[Field]:
    return [Field(*s) for s in spec]


# --- the per-tick rule's io vector: inputs, then outputs -----------------------------------------
INPUTS = _fields(
    ("t", 1, "tick time, s"),
    ("now", 1, "when the torque is sent, on the time axis of t, s"),
    ("q", 2, "measured joint angles, rad"),
    ("dq", 2, "measured joint velocities, rad/s"),
    ("f", 2, "measured image features, px"),
    ("state_age", 1, "s before now the state was sampled; 0 or less: as measured"),
    ("f_age", 1, "s before now the features were captured; 0 or less: as measured"),
    ("f_stale", 1, "flag 0.0 / 1.0"),
    ("state_stale", 1, "flag 0.0 / 1.0"),
    ("enabled", 1, "flag: the drive is in operation enabled"),
)
OUTPUTS = _fields(
    ("q_pred", 2, "Joint angles the hold or the law acted on, rad: q brought up to the tick over "
     "predict_ms (q itself when predict_ms is 0); null when neither ran.", "vector"),
    ("dq_pred", 2, "Joint velocities the hold or the law acted on, rad/s (see q_pred).", "vector"),
    ("f_pred", 2, "Image features the law acted on, px: f brought up to the tick over "
     "f_predict_ms (f itself when f_predict_ms is 0); null when the law did not run.", "vector"),
    ("xi", 2, "Filtered state xi of eq. (11).", "vector"),
    ("u", 2, "Law output u, N m.", "vector"),
    ("tau", 2, "Torque sent (after saturation), N m.", "vector"),
    ("tau_saturated", 1, "tau was clipped to robot.tau_max.", "boolean"),
    ("mode", 1, "Law that produced this tick's command: pbc | ioc | rhc (the daemon may report "
     "another name, e.g. hold, on stale inputs).", "law"),
    ("residual", 1, "Solver optimality residual (0 for closed-form laws); null when unknown.",
     "number"),
    ("iterations", 1, "GMRES iterations this tick; null when unknown.", "integer"),
    ("fallback", 1, "The tick fell back to the inverse-optimal law (eq. 27).", "boolean"),
    ("cost", 1, "Stage cost l(x, u) of eq. (25); J = sum(cost) / rate; null when unknown.",
     "number"),
    ("V", 1, "Energy function V of eq. (13); null when unknown.", "number"),
    ("tau_raw", 2, "the torque of eq. (11) before saturation"),
)  # fmt: skip
IO = Block("IO", "The per-tick rule's io vector: inputs, then outputs.", INPUTS + OUTPUTS)
IO.OUTPUTS = IO.SIZE - sum(f.size for f in OUTPUTS)
"""The first output (Controller.decide fills the inputs, 0 .. OUTPUTS, in one assignment)."""

MODE_CONTROL, MODE_HOLD, MODE_NO_STATE, MODE_DRIVE = 0.0, 1.0, 2.0, 3.0
"""``control``: the law ran; ``hold``: no usable features (joint damper); ``no_state``: no joint
state (zero torque); ``drive``: the DSP is not in operation enabled (zero torque)."""
MODE_NAMES = ("control", "hold", "no_state")
"""The names of the modes below ``MODE_DRIVE`` (which is named by the drive's mode)."""

# --- the rule's limits and its own state ----------------------------------------------------------
LIM = Block(
    "LIM",
    "The per-tick rule's limits (from the configuration).",
    _fields(
        ("tau_max", 2, "amplifier limits, N m"),
        ("u_max", 2, "C/GMRES input bounds, N m"),
        ("law", 1, "LAW_CODES of the law"),
        ("horizon", 1, "oldest measurement worth compensating, s"),
        ("step", 1, "longest Runge-Kutta step of the prediction, s"),
    ),
)
KS = Block(
    "KS",
    "The per-tick rule's own state.",
    _fields(
        ("holding", 1, "1: the last tick held or the drive was off; the law restarts"),
        ("t0", 1, "when the law started (NaN: not yet), s"),
        ("n", 1, "torques in the history"),
        ("fallbacks", 1, "ticks that fell back to eq. (27) since the law started"),
    ),
)

# --- the model's and the solver's parameters: one layout ------------------------------------------
PAR = Block(
    "PAR",
    "Float parameters of every compiled kernel: the nominal model, then the rhc settings.",
    _fields(
        ("th1", 1, "theta1 of M(q)"),
        ("th2", 1, "theta2"),
        ("th3", 1, "theta3"),
        ("l1", 1, "link 1, m"),
        ("l2", 1, "link 2, m"),
        ("gain", 1, "camera gain s lambda / z_wo"),
        ("kp", 1, "feature gain"),
        ("g1", 1, "gravity term 1"),
        ("g2", 1, "gravity term 2"),
        ("alpha", 4, "alpha, 2x2 row-major"),
        ("r", 4, "R, 2x2 row-major"),
        ("r_inv", 4, "R^-1, 2x2 row-major"),
        ("u_max", 2, "input bounds"),
        ("rv", 1, "dummy weight"),
        ("vmin", 2, "floor of the dummy inputs"),
        ("hfd", 1, "forward-difference step"),
        ("zeta", 1, "continuation gain, 1/s"),
        ("dt", 1, "control period, s"),
        ("tf", 1, "final horizon, s"),
        ("growth", 1, "a of T(t) = Tf (1 - exp(-a t))"),
        ("init_tol", 1, "residual target of the initial Newton solve"),
        ("res_bound", 1, "largest residual of a solution applied"),
    ),
)
# --- the solver's state vector (U and Udot follow the head) ---------------------------------------
ST = Block(
    "ST",
    "The C/GMRES solver's state vector: inputs, flags and outputs of a tick, then U and Udot.",
    _fields(
        ("x", 6, "measured state x"),
        ("xdot", 6, "given state motion, used when model_xdot is 0"),
        ("u", 2, "out: input to apply"),
        ("t", 1, "solver time, s"),
        ("init", 1, "1: solve from scratch (Newton-GMRES) first; out: 1 if not accepted"),
        ("model_xdot", 1, "1: predict the state motion with eq. (12)"),
        ("res", 1, "out: ||F|| at the applied solution"),
        ("iters", 1, "out: forward-difference products spent in GMRES"),
        ("fevals", 1, "out: evaluations of F (sweep pairs) this tick"),
        ("spare", 4, "room for new head fields without moving U"),
    ),
)
ST.HEAD = ST.SIZE

# --- the optimal control problem's vectors, per horizon stage -------------------------------------
XS = Block(
    "XS",
    "The prediction state x of eq. (12) in (q, xi, f) coordinates; its costate lam likewise.",
    _fields(("q", 2, "joint angles, rad"), ("xi", 2, "xi of eq. (11)"), ("f", 2, "features, px")),
)
STAGE = Block(
    "STAGE",
    "The unknowns of one horizon stage in U (and in F, its KKT rows), Ohtsuka's dummy inputs.",
    _fields(
        ("u", 2, "input u_k, N m"),
        ("v", 2, "dummy inputs of the bounds u_i^2 + v_i^2 = umax_i^2"),
        ("mu", 2, "multipliers of the bounds"),
    ),
)
AUX = Block(
    "AUX",
    "Intermediates of one Euler substep kept from the forward sweep for the backward sweep.",
    _fields(
        ("s2", 1, "sin q2"),
        ("c2", 1, "cos q2"),
        ("e1", 1, "eta1"),
        ("e2", 1, "eta2"),
        ("dq1", 1, "dq1 = xi1 + (alpha eta)_1"),
        ("dq2", 1, "dq2"),
        ("y1", 1, "xi1'"),
        ("y2", 1, "xi2'"),
        ("m11", 1, "M11(q)"),
        ("m12", 1, "M12(q)"),
        ("idet", 1, "1 / det M(q)"),
        ("k1", 1, "C(q, dq) xi / (t3 s2), row 1"),
        ("k2", 1, "row 2"),
    ),
)
PRE = Block(
    "PRE",
    "The block preconditioner of one stage (rhc.residual.precond_setup).",
    _fields(
        ("s_inv", 4, "inverse of the reduced 2x2 system in du, row-major"),
        ("uv", 2, "u_i / v_i"),
        ("mv", 2, "mu_i / v_i"),
        ("iv", 2, "1 / v_i"),
    ),
)


# --- the solver's work vector -------------------------------------------------------------------
@dataclass(frozen=True)
class WorkArray:
    """One array cut out of the work vector: ``rows x cols`` from the sizes (N, S, n = 6 N,
    m = the larger Krylov dimension)."""

    name: str
    rows: Callable[[int, int, int, int], int]
    cols: Callable[[int, int, int, int], int]


VEC = Block(
    "VEC",
    "The rows of the work array vecs: vectors of length n = 6 N.",
    _fields(
        ("f", 1, "F at U"),
        ("fs", 1, "F at the state moved along xdot"),
        ("b", 1, "right-hand side of the correction"),
        ("du", 1, "the correction, a Newton step"),
        ("utry", 1, "U of a backtracking trial"),
        ("ftry", 1, "F there"),
        ("ut", 1, "U + h v of a forward-difference product"),
        ("z", 1, "preconditioned basis vector"),
        ("zz", 1, "its solution part"),
        ("b2", 1, "right-hand side of the prediction"),
        ("d2", 1, "the prediction"),
    ),
)
SMALL = Block(
    "SMALL",
    "The rows of the work array small (m + 1 each): GMRES's rotations and its small system.",
    _fields(("cs", 1, "cosines"), ("sn", 1, "sines"), ("g", 1, "rotated residual"), ("y", 1, "y")),
)
NX, NS, NAUX, NVEC, NPRE = XS.SIZE, STAGE.SIZE, AUX.SIZE, VEC.SIZE, PRE.SIZE
"""State dimension; unknowns per stage; intermediates of a stage kept from the forward sweep;
work vectors of length 6N; floats per stage of the block preconditioner."""

WORK = (
    WorkArray("X", lambda N, S, n, m: N * S + 1, lambda N, S, n, m: NX),
    WorkArray("Lam", lambda N, S, n, m: N * S + 1, lambda N, S, n, m: NX),
    WorkArray("Vb", lambda N, S, n, m: m + 2, lambda N, S, n, m: n),
    WorkArray("Hs", lambda N, S, n, m: m + 2, lambda N, S, n, m: m),
    WorkArray("small", lambda N, S, n, m: SMALL.SIZE, lambda N, S, n, m: m + 1),
    WorkArray("G", lambda N, S, n, m: m + 2, lambda N, S, n, m: 2),
    WorkArray("Ys", lambda N, S, n, m: 2, lambda N, S, n, m: m + 2),
    WorkArray("vecs", lambda N, S, n, m: NVEC, lambda N, S, n, m: n),
    WorkArray("pre", lambda N, S, n, m: 1, lambda N, S, n, m: NPRE * N),
    WorkArray("xs", lambda N, S, n, m: 1, lambda N, S, n, m: NX),
    WorkArray("hx", lambda N, S, n, m: 1, lambda N, S, n, m: NX),
    WorkArray("hu", lambda N, S, n, m: 1, lambda N, S, n, m: NX),
    WorkArray("cnt", lambda N, S, n, m: 1, lambda N, S, n, m: 1),
    WorkArray("Aux", lambda N, S, n, m: N * S, lambda N, S, n, m: NAUX),
)
"""The work vector of one tick, in order (:func:`~rt_controller.control.rhc.kernel.rhc_tick`
finds each array by its index here: :data:`W`)."""
W = Block("W", "Index of each work array in WORK.", [Field(a.name) for a in WORK])
CUT = Block(
    "CUT",
    "Where one WORK array lies in the work vector (IP.WORK holds one per array, in order).",
    _fields(("off", 1, "offset"), ("rows", 1, "rows"), ("cols", 1, "columns")),
)

IP = Block(
    "IP",
    "Integer parameters of the solver, and where its work arrays lie in the work vector.",
    _fields(
        ("n", 1, "horizon steps N"),
        ("kmax", 1, "GMRES iterations per tick"),
        ("init_iters", 1, "Newton iterations of the initial solve"),
        ("init_krylov", 1, "Krylov dimension of one Newton step"),
        ("sub", 1, "Euler substeps per stage"),
        ("work", CUT.SIZE * len(WORK), "the CUT of each WORK array, in order"),
    ),
)


def work_offsets(steps: int, substeps: int, krylov: int) -> tuple[np.ndarray, int]:
    """(offset, rows and columns of each :data:`WORK` array, in order; the work vector's
    length) for N = ``steps``, S = ``substeps`` and m = ``krylov``."""
    n = NS * steps
    out = np.zeros(IP.field("work").size, dtype=np.int64)
    off = 0
    for i, a in enumerate(WORK):
        rows, cols = a.rows(steps, substeps, n, krylov), a.cols(steps, substeps, n, krylov)
        o = CUT.SIZE * i
        out[o + CUT.OFF], out[o + CUT.ROWS], out[o + CUT.COLS] = off, rows, cols
        off += rows * cols
    return out, off


def work_length(iP: np.ndarray) -> int:
    """The work vector's length for the cut in ``iP`` (:data:`IP`): the end of its last array."""
    last = IP.WORK + CUT.SIZE * (len(WORK) - 1)
    return int(iP[last + CUT.OFF] + iP[last + CUT.ROWS] * iP[last + CUT.COLS])


def pack_params(model: NominalModel) -> np.ndarray:
    """The model's numbers in a :data:`PAR` vector; the rhc settings are left zero (filled by
    :func:`rt_controller.control.rhc.problem.pack_params`)."""
    p = np.zeros(PAR.SIZE)
    p[PAR.TH1], p[PAR.TH2], p[PAR.TH3] = model.theta1, model.theta2, model.theta3
    p[PAR.L1], p[PAR.L2], p[PAR.GAIN], p[PAR.KP] = model.l1, model.l2, model.gain, model.kp
    p[PAR.G1], p[PAR.G2] = model.gravity1, model.gravity2
    p[PAR.ALPHA : PAR.ALPHA + 4] = np.asarray(model.alpha, dtype=float).ravel()
    p[PAR.R : PAR.R + 4] = np.asarray(model.R, dtype=float).ravel()
    p[PAR.R_INV : PAR.R_INV + 4] = np.asarray(model.R_inv, dtype=float).ravel()
    return p
