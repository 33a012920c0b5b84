"""Step-size control shared by the implicit integrators.

An integrator of order p reports, for a trial step h from (ε_n, ε̇_n), a
local error estimate e of the coordinates (O(h^{p+1})). Its size is the
weighted RMS norm PETSc's TS uses (``TSErrorWeightedNorm2``),

    ‖e‖ = sqrt( (1/N) Σ_i ( e_i / (atol + rtol · max(|ε_n,i|, |ε_{n+1},i|)) )² ),

and the step is accepted when ‖e‖ ≤ 1. Either way the next step is

    h_new = h · min(f_max, max(f_min, safety · ‖e‖^{−1/(p+1)})),

with f_max = 1 right after a rejection (Hairer, Nørsett & Wanner, *Solving
Ordinary Differential Equations I*, §II.4). A Newton failure counts as a
rejection and halves h. With ``adaptive=False`` every step is ``dt`` (the
last one shortened to land on ``t_stop``) and no error is estimated.
"""

import math

import numpy as np

__all__ = ["StepControl", "PositionHistory"]


class StepControl:
    """Step sizes for one integrator: fixed ``dt`` or error-controlled.

    Parameters
    ----------
    dt : float
        The fixed step, or the first trial step when ``adaptive``.
    adaptive : bool
    rtol, atol : float
        Relative and absolute (metres) tolerances of the local error.
    dt_min, dt_max : float
        Bounds of the adaptive step; a step that must go below dt_min fails.
    """

    safety, f_min, f_max = 0.9, 0.2, 2.0

    def __init__(self, dt, adaptive=False, rtol=1e-3, atol=1e-5, dt_min=1e-9,
                 dt_max=np.inf):
        self.dt, self.adaptive = float(dt), adaptive
        self.rtol, self.atol = rtol, atol
        self.dt_min, self.dt_max = dt_min, dt_max
        self.rejected, self.failed = 0, 0
        self.after_reject = False
        self.last_error = 0.0

    def propose(self, t, t_stop):
        """The trial step from t, and whether it lands on t_stop.

        A step within 1e-8 relative of the distance to t_stop takes exactly
        that distance; an adaptive step that would leave less than its own
        length to go takes half of the rest instead, so no sliver is left.
        """
        h = min(self.dt, self.dt_max)
        if t_stop is None:
            return h, False
        rest = t_stop - t
        if rest <= h * (1.0 + 1e-8):
            return rest, True
        if self.adaptive and rest < 2.0 * h:
            return 0.5 * rest, False
        return h, False

    def norm(self, comm, e, x0, x1):
        """Weighted RMS norm ‖e‖ of local arrays (collective)."""
        w = self.atol + self.rtol * np.maximum(np.abs(x0), np.abs(x1))
        local = np.array([np.sum((e / w) ** 2), e.size], dtype=float)
        total = comm.tompi4py().allreduce(local)
        return float(np.sqrt(total[0] / max(total[1], 1.0)))

    def judge(self, err, h, order, landed):
        """Accept or reject a step of error ``err``; set the next trial step,
        never below dt_min. Returns None when a step already at dt_min (or a
        shorter one landing on t_stop) is rejected: no step above dt_min
        meets the tolerance.

        A step that landed on t_stop does not shrink the step after it.
        """
        self.last_error = err
        fac = self.safety * max(err, 1e-10) ** (-1.0 / (order + 1))
        fac = min(1.0 if self.after_reject else self.f_max, max(self.f_min, fac))
        if err <= 1.0:
            self.after_reject = False
            self.dt = max(h, self.dt) * fac if landed else h * fac
            self.dt = max(min(self.dt, self.dt_max), self.dt_min)
            return True
        self.rejected += 1
        self.after_reject = True
        if h <= self.dt_min * (1.0 + 1e-12):
            return None
        self.dt = max(h * fac, self.dt_min)
        return False

    def newton_failed(self, h):
        """A trial step whose Newton solve failed: halve it. Returns False
        when the halved step would be below dt_min."""
        self.failed += 1
        self.rejected += 1
        self.after_reject = True
        self.dt = 0.5 * h
        return self.dt >= self.dt_min

    def state(self):
        """What the next step needs beyond (t, ε, ε̇), for checkpoints: floats
        under keys ``control_*``."""
        return dict(control_dt=self.dt, control_rejected=float(self.rejected),
                    control_failed=float(self.failed),
                    control_after_reject=float(self.after_reject),
                    control_last_error=self.last_error)

    def set_state(self, st):
        """Restore from a dict holding (at least) the keys of ``state``."""
        self.dt = float(st["control_dt"])
        self.rejected = int(st["control_rejected"])
        self.failed = int(st["control_failed"])
        self.after_reject = bool(st["control_after_reject"])
        self.last_error = float(st["control_last_error"])


class PositionHistory:
    """Local error of an order-p step from the last p + 1 accepted positions.

    The polynomial through (t_{n−i}, ε_{n−i}), i = 0 … p, extrapolated to
    t_{n+1} errs by −ε^{(p+1)} Π/(p+1)!, Π = Π_i (t_{n+1} − t_{n−i}), and a
    method whose local error is c h^{p+1} ε^{(p+1)} gives

        e = c h^{p+1} / (c h^{p+1} + Π/(p+1)!) · (ε_{n+1} − ε_pred)

    (Milne's device). Only positions enter, so a stiff mode far above 1/h —
    the yarns' axial vibration, whose amplitude in ε is tiny while its
    acceleration is not — does not drive the step down, as an estimate from
    accelerations would. Until p + 1 positions are known ``estimate``
    returns False and the integrator uses its own one-step estimate.
    """

    def __init__(self, order, constant):
        self.order, self.constant = order, constant
        self.x, self.t = [], []          # newest last; times relative to t_n

    def estimate(self, x_new, h, out):
        """e of the trial step h ending at x_new (local arrays) into out."""
        if len(self.x) < self.order + 1:
            return False
        tn = np.array(self.t)            # t_{n−i} − t_n, ≤ 0
        pred = np.zeros_like(x_new)
        for i, (xi, ti) in enumerate(zip(self.x, tn)):
            w = np.prod([(h - tj) / (ti - tj) for j, tj in enumerate(tn) if j != i])
            pred += w * xi
        P = np.prod(h - tn) / math.factorial(self.order + 1)
        ch = self.constant * h ** (self.order + 1)
        out[:] = ch / (ch + P) * (x_new - pred)
        return True

    def push(self, x_new, h):
        """Record an accepted step h ending at x_new (copied)."""
        self.t = [t - h for t in self.t] + [0.0]
        self.x.append(np.array(x_new, copy=True))
        if len(self.x) > self.order + 1:
            self.x.pop(0)
            self.t.pop(0)

    def start(self, x0):
        if not self.x:
            self.push(x0, 0.0)

    def state(self):
        """Positions (stacked) and their times, for checkpoints."""
        st = {"history_t": np.array(self.t + [np.nan] * (self.order + 1 - len(self.t)))}
        for i in range(self.order + 1):
            st[f"history_x{i}"] = (self.x[i] if i < len(self.x)
                                   else np.full_like(self.x[0], np.nan))
        return st

    def set_state(self, st):
        t = st["history_t"]
        k = int(np.sum(~np.isnan(t)))
        self.t = [float(v) for v in t[:k]]
        self.x = [np.array(st[f"history_x{i}"], copy=True) for i in range(k)]
