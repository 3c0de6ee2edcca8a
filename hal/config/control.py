"""The controller's sections: ``[gains]`` (eq. 34), ``[rhc]`` (C/GMRES, eq. 30) and
``[controller]`` (the daemon), and the names of the control laws."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from hal.config.values import Mat2, Vec2

LAW_NAMES = ("pbc", "ioc", "rhc")
"""Control-law names (``controller.law``, ``--law``); the compiled rule has one code per name
(``rt_controller.control.decide_kernel.LAW_CODES``, checked by a test)."""

if TYPE_CHECKING:  # numpy is imported where used: `hil --help` does not need it
    import numpy as np


@dataclass(frozen=True)
class GainsConfig:
    """Controller gains of eq. (11), (13), (15), (18) and (34)."""

    kp: float = 0.13
    alpha: Mat2 = ((0.05, 0.0), (0.0, 0.15))
    K: Mat2 = ((0.01, 0.0), (0.0, 0.01))

    @property
    def R(self) -> np.ndarray:
        """R = kp/4 alpha^-1 + K (eq. 18)."""
        import numpy as np

        return self.kp / 4.0 * np.linalg.inv(np.array(self.alpha)) + np.array(self.K)


@dataclass(frozen=True)
class RhcConfig:
    """Receding-horizon control (eq. 30) solved by C/GMRES."""

    horizon: float = 0.1
    """Final horizon length T_f, s."""
    steps: int = 10
    """Number of discretisation steps N of the horizon."""
    kmax: int = 5
    """GMRES iterations per update."""
    zeta: float = 50.0
    """Continuation stabilisation gain, 1/s (dF/dt = -zeta F)."""
    horizon_growth: float = 0.0
    """a in T(t) = T_f (1 - exp(-a t)); 0 keeps T = T_f from the start."""
    u_max: Vec2 = (150.0, 15.0)
    """Bounds |u_i| <= u_max,i enforced with dummy inputs, N·m."""
    dummy_weight: float = 0.01
    """Weight of the dummy inputs in the cost (keeps the bound multipliers finite)."""
    fd_step: float = 1e-8
    """Forward-difference step of the GMRES matrix-free products."""
    residual_bound: float = 1e3
    """Above this optimality residual the solution is rejected and the tick falls back."""
    init_tol: float = 1e-8
    """Residual target of the initial Newton-GMRES solve."""
    init_iterations: int = 50
    """Iteration limit of the initial Newton-GMRES solve."""


@dataclass(frozen=True)
class ControllerConfig:
    """Controller daemon settings."""

    law: str = "ioc"
    """pbc | ioc | rhc."""
    clock: str = "realtime"
    """realtime | lockstep."""
    feature_timeout_s: float = 0.1
    """Features older than this are stale."""
    outage_warn_periods: int = 5
    """A camera outage: more than this many ticks in a row on stale or invalid features. Each
    is a warning naming its start, its length and the longest (realtime and lockstep alike)."""
    outage_max_share: float = 0.25
    """A run that spent more than this share of its ticks (0-1) on stale or invalid features
    is not clean: its J is not the paper's experiment's."""
    state_timeout_s: float = 0.05
    """Joint states older than this mean the DSP went silent."""
    predict_state: bool = True
    """Realtime: bring the joint state up to the tick before the law sees it (the nominal model
    driven by the torques sent since the state arrived; the cycle record's ``predict_ms``). A
    tick that runs on the previous period's state (``late_states``) otherwise acts on a whole
    period of delay, which the paper's IOC and RHC gains do not tolerate. Lockstep states are
    sampled at the tick and are never predicted."""
    predict_features: bool = True
    """Realtime: bring the image features up to the tick before the law sees them: the target
    (static) seen from the predicted pose of now instead of the pose at capture (eq. 6; the
    cycle record's ``f_predict_ms``). Vision, zenoh and the camera make features one to three
    periods old on a busy host."""
    spin_us: float = 300.0
    """Busy-wait for the last microseconds before a deadline."""
    rt_priority: int = 80
    """SCHED_FIFO priority (best effort)."""
    cpu: int = -1
    """CPU to pin the loop to; -1 = leave affinity alone."""
    log_dir: str = "logs"
    """Where a run without ``--log`` logs: ``run-YYYYmmdd-HHMMSS-LAW.mcap`` (``-2``, ``-3``, ...
    when a run of the same second has the name)."""
    max_clock_skew_s: float = 0.005
    """A feature message stamped further than this in the future (receive clock) is rejected
    (``future_stamp``): its age would come out negative and defeat the stale check."""
    feature_source_takeover_s: float = 1.0
    """After the first feature source id is locked in, another source id is rejected
    (``foreign_source``) unless the locked source sent nothing accepted for this long (a
    restarted vision process); 0 lets any new source take over at once."""
    rearm_after_trip: bool = True
    """Reset and re-enable the DSP once after each watchdog fault it reports (the trip means
    this loop was late); false leaves the amplifiers off. The run still counts as not clean."""
    rearm_after_restart: bool = False
    """Re-enable a DSP that restarted (new session) or was disabled by another node. Default:
    no: the controller holds zero torque, reports the mode and exits non-zero."""
