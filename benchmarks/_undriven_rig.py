"""The real-rig-like cart-pole of :mod:`benchmarks.undriven` (issue #41).

:func:`camera_cartpole` simulates what a camera-tracked cart-pole rig logs (frame
stamps with jitter, dropped frames and glitches, the cart in pixels, a bang-bang
command acting after an actuator delay, cart friction, motionless stretches);
:func:`camera_pipeline` is a user's path from that log to ``fit``;
:func:`rig_truth_in_pixels` and :func:`rig_model_in_pixels` give the true model in
that path's units, and :func:`rollouts` scores a model by 1 s rollouts. Re-exported
by :mod:`benchmarks.undriven`; ``tests/_undriven.py`` wraps them at test sizes.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

G = 9.81


def warning_text(caught) -> list:
    """``"Class: first words"`` of each distinct warning."""
    out = []
    for w in caught:
        if issubclass(w.category, (DeprecationWarning, FutureWarning)):
            continue
        words = " ".join(str(w.message).split()[:8])
        text = f"{w.category.__name__}: {words}"
        if text not in out:
            out.append(text)
    return out


def r_squared(true, pred) -> float:
    """R^2 of ``pred`` against ``true`` (NaN when ``true`` is constant)."""
    true, pred = np.asarray(true, float), np.asarray(pred, float)
    ss = float(np.sum((true - true.mean()) ** 2))
    return 1.0 - float(np.sum((true - pred) ** 2)) / ss if ss > 0 else float("nan")


@dataclass
class CameraRecords:
    """Records of :func:`camera_cartpole`, as a camera rig's log would hold them.

    Attributes
    ----------
    t : ndarray of shape (n_rows,)
        Recorded frame stamps (s), restarting at each record, glitches included.
    x_px : ndarray of shape (n_rows,)
        Cart position in pixels (``px_per_m * x + offset_px`` plus noise).
    theta : ndarray of shape (n_rows,)
        Pole angle (rad, 0 hanging) plus noise.
    u : ndarray of shape (n_rows,)
        The logged command (V) at each frame, before the actuator delay.
    groups : ndarray of shape (n_rows,)
        Record index.
    state : ndarray of shape (n_rows, 4)
        True ``[x (m), theta, x_dot, theta_dot]`` at each frame's capture time.
    t_true : ndarray of shape (n_rows,)
        True capture times.
    truth : dict
        The simulator's parameters (masses, gain, delay, friction, scale, ...).
    glitches : list of tuple
        ``(record, stamp, kind)`` of each time-stamp glitch.
    """

    t: np.ndarray
    x_px: np.ndarray
    theta: np.ndarray
    u: np.ndarray
    groups: np.ndarray
    state: np.ndarray
    t_true: np.ndarray
    truth: dict
    glitches: list = field(default_factory=list)


GLITCH_KINDS = ("stall", "late", "duplicate", "backwards")


def rig_system(truth: dict):
    """The true cart-pole of :func:`camera_cartpole` in SI units (input: force, N)."""
    from lagsindy.systems import cart_pendulum

    system = cart_pendulum(truth["cart_mass"], truth["pole_mass"], truth["length"], G)
    return system.with_damping(
        viscous={"x": truth["viscous"]},
        coulomb={"x": truth["coulomb"]},
        eps=truth["coulomb_eps"],
    )


def camera_cartpole(
    n_records: int = 8,
    duration: float = 10.0,
    *,
    cart_mass: float = 1.0,
    pole_mass: float = 0.05,
    length: float = 0.3,
    gain: float = 1.5,
    voltage: float = 3.0,
    delay: float = 0.02,
    viscous: float = 8.0,
    coulomb: float = 0.6,
    coulomb_eps: float = 0.01,
    px_per_m: float = 800.0,
    offset_px: float = 320.0,
    rate: float = 65.0,
    jitter: float = 0.5e-3,
    n_dropped: int = 6,
    n_glitches: int = 4,
    rest: tuple = (2.0, 4.0),
    rest_every: int = 2,
    switch: tuple = (0.2, 0.9),
    noise_px: float = 0.5,
    noise_rad: float = 2e-3,
    random_state=None,
) -> CameraRecords:
    """Simulate a camera-tracked cart-pole rig driven by a bang-bang voltage.

    The cart (``cart_mass``, viscous ``viscous`` N s/m and Coulomb ``coulomb`` N
    friction, smoothed over ``coulomb_eps`` m/s) carries an undriven point-mass pole
    (``pole_mass`` on ``length``). The logged command switches between
    ``+-voltage`` after random dwell times ``U(*switch)``; the cart feels
    ``gain * u(t - delay)`` (N). Every ``rest_every``-th record starts with
    ``U(*rest)`` seconds at rest (command 0, pole hanging still); the others start
    at once with the pole at a small random angle. Frames are captured at ``rate``
    Hz with Gaussian stamp ``jitter`` (s); ``n_dropped`` single frames are lost
    (over all records) and ``n_glitches`` time-stamp glitches are added, cycling
    through :data:`GLITCH_KINDS`: ``"stall"`` (0.3 s without frames, stamps
    right), ``"late"`` (a frame stamped 0.6 frame late), ``"duplicate"`` (a frame's
    image is the previous one's) and ``"backwards"`` (a stamp 2 ms before the
    previous one). The cart is logged in pixels, ``px_per_m * x + offset_px`` with
    ``noise_px`` noise, the angle with ``noise_rad``. Deterministic given
    ``random_state``.

    Returns
    -------
    CameraRecords
    """
    rng = np.random.default_rng(random_state)
    truth = dict(
        cart_mass=cart_mass,
        pole_mass=pole_mass,
        length=length,
        gain=gain,
        voltage=voltage,
        delay=delay,
        viscous=viscous,
        coulomb=coulomb,
        coulomb_eps=coulomb_eps,
        px_per_m=px_per_m,
        offset_px=offset_px,
        rate=rate,
    )
    system = rig_system(truth)
    dt = 1.0 / rate
    glitch_at = rng.choice(n_records, size=n_glitches, replace=n_glitches > n_records)
    drop_at = rng.choice(n_records, size=n_dropped)
    cols = {k: [] for k in ("t", "t_true", "u", "state", "img", "g")}
    glitches = []
    for r in range(n_records):
        t_rest = rng.uniform(*rest) if r % rest_every == 0 else 0.0
        n = int(duration * rate)
        t_cap = np.arange(n) * dt + np.clip(rng.normal(0, jitter, n), -dt / 4, dt / 4)
        t_cap[0] = 0.0
        # command: 0 while at rest, then +-voltage, switching after random dwells
        switches = [t_rest]
        while switches[-1] < duration + 1.0:
            switches.append(switches[-1] + rng.uniform(*switch))
        switches = np.asarray(switches)
        signs = rng.choice([-1.0, 1.0]) * (-1.0) ** np.arange(len(switches))

        def command(tt, switches=switches, signs=signs, t_rest=t_rest):
            k = np.searchsorted(switches, tt, side="right") - 1
            return np.where(np.asarray(tt) < t_rest, 0.0, voltage * signs[k])

        x0 = np.zeros(4)
        if t_rest == 0.0:
            x0[1] = rng.uniform(-0.3, 0.3)
        state = _simulate_pieces(
            system, x0, t_cap, switches + delay, command, delay, gain
        )
        u = command(t_cap)
        keep = np.ones(n, bool)
        for _ in range(int(np.sum(drop_at == r))):  # dropped single frames
            keep[rng.integers(5, n - 5)] = False
        t_rec = t_cap.copy()
        img = state.copy()
        for k, kind in enumerate(GLITCH_KINDS * n_glitches):
            if k >= n_glitches or glitch_at[k] != r:
                continue
            i = int(rng.integers(int(0.2 * n), int(0.8 * n)))
            if kind == "stall":
                keep[i : i + int(0.3 * rate)] = False
            elif kind == "late":
                t_rec[i] += 0.6 * dt
            elif kind == "duplicate":
                img[i] = img[i - 1]
            else:
                t_rec[i] = t_rec[i - 1] - 0.002
            glitches.append((r, float(t_rec[i]), kind))
        cols["t"].append(t_rec[keep])
        cols["t_true"].append(t_cap[keep])
        cols["u"].append(u[keep])
        cols["state"].append(state[keep])
        cols["img"].append(img[keep])
        cols["g"].append(np.full(int(keep.sum()), r))
    img = np.concatenate(cols["img"])  # a duplicated frame shows the previous one
    x_px = px_per_m * img[:, 0] + offset_px
    x_px = x_px + noise_px * rng.standard_normal(len(x_px))
    theta = img[:, 1] + noise_rad * rng.standard_normal(len(x_px))
    return CameraRecords(
        t=np.concatenate(cols["t"]),
        x_px=x_px,
        theta=theta,
        u=np.concatenate(cols["u"]),
        groups=np.concatenate(cols["g"]),
        state=np.concatenate(cols["state"]),
        t_true=np.concatenate(cols["t_true"]),
        truth=truth,
        glitches=glitches,
    )


def _simulate_pieces(system, x0, t_out, breaks, command, delay, gain):
    """Integrate between the instants where the delayed command switches, so every
    integration step sees a constant force; states at ``t_out``."""
    edges = np.unique(
        np.concatenate([[t_out[0]], breaks[breaks < t_out[-1]], [t_out[-1]]])
    )
    out = np.empty((len(t_out), 4))
    out[0] = x0
    state = np.asarray(x0, float)
    for a, b in zip(edges[:-1], edges[1:]):
        force = gain * float(command(0.5 * (a + b) - delay))
        inside = t_out[(t_out > a) & (t_out <= b)]
        tt = np.unique(np.concatenate([[a], inside, [b]]))
        traj = system.simulate(state, tt, lambda _t, _s, f=force: np.array([f]))
        if len(inside):
            out[np.searchsorted(t_out, inside)] = traj[np.searchsorted(tt, inside)]
        state = traj[-1]
    return out


def camera_pipeline(rec: CameraRecords):
    """A user's path from the log to ``fit``: ``(X, tau, groups, t, notes)``.

    Rows whose stamp is not after the previous kept stamp of the record are dropped
    (:func:`lagsindy.derivatives` needs increasing times); derivatives of
    ``[x_px, theta]`` come from the stamps (P-spline, ``theta`` an angle), records
    cut at their gaps (``return_groups=True``); tau is ``[u, 0]``: the logged
    command on the cart, a column of zeros for the undriven pole. ``notes`` lists
    the warnings of the derivatives.
    """
    from lagsindy import derivatives

    keep = np.ones(len(rec.t), bool)
    for g in np.unique(rec.groups):
        rows = np.flatnonzero(rec.groups == g)
        last = -np.inf
        for i in rows:
            if rec.t[i] > last:
                last = rec.t[i]
            else:
                keep[i] = False
    q = np.column_stack([rec.x_px, rec.theta])[keep]
    t = rec.t[keep]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        X, groups = derivatives(
            q, t, groups=rec.groups[keep], angles=[1], return_groups=True
        )
    tau = np.column_stack([rec.u[keep], np.zeros(int(keep.sum()))])
    notes = [f"dropped {int((~keep).sum())} rows with a non-increasing stamp"]
    notes += warning_text(caught)
    return X, tau, groups, t, notes


def rig_truth_in_pixels(truth: dict) -> dict:
    """The four Lagrangian coefficients in the units of the default path: x in px,
    the input in V.

    With ``x_px = s x + offset`` the generalized force on ``x_px`` is ``F / s`` and
    ``F = gain u``, so ``u`` is the force of the Lagrangian ``L * s / gain``.
    """
    m, mc, length, s = (
        truth[k] for k in ("pole_mass", "cart_mass", "length", "px_per_m")
    )
    k = s / truth["gain"]
    return {
        "x_dot**2": k * (mc + m) / 2 / s**2,
        "theta_dot**2": k * m * length**2 / 2,
        "theta_dot*x_dot*cos(theta)": k * m * length / s,
        "cos(theta)": k * m * G * length,
    }


def rig_model_in_pixels(truth: dict):
    """The true rig as a :class:`~lagsindy.MechanicalModel` in the default path's
    units (x in px, inputs ``[u (V), 0]``): the reference a learned model is judged
    against."""
    import sympy as sp

    from lagsindy import MechanicalModel

    c = rig_truth_in_pixels(truth)
    x_dot, theta, theta_dot = sp.symbols("x_dot theta theta_dot", real=True)
    s, k = truth["px_per_m"], truth["px_per_m"] / truth["gain"]
    lagrangian = (
        c["x_dot**2"] * x_dot**2
        + c["theta_dot**2"] * theta_dot**2
        + c["theta_dot*x_dot*cos(theta)"] * theta_dot * x_dot * sp.cos(theta)
        + c["cos(theta)"] * sp.cos(theta)
    )
    dissipation = k * truth["viscous"] / s**2 * x_dot**2 / 2
    coulomb = -k / s * truth["coulomb"] * sp.tanh(x_dot / (truth["coulomb_eps"] * s))
    return MechanicalModel(
        lagrangian,
        ["x", "theta"],
        dissipation=dissipation,
        forces=[coulomb, 0],
        name="rig (true, px and V)",
    )


def rollouts(model, X, tau, groups, t, horizon=1.0, max_windows=40):
    """Median RMS errors of ``horizon`` s rollouts from the estimated states.

    Returns ``(theta error, x error (px), fraction that simulated, theta error of
    holding the initial state)``; windows start every ``horizon`` s in each segment.
    """
    errs, xerrs, hold, ok, n = [], [], [], 0, 0
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        tg = t[rows]
        start = 0
        while start < len(rows) and n < max_windows:
            stop = int(np.searchsorted(tg, tg[start] + horizon, side="right"))
            if tg[stop - 1] - tg[start] < 0.8 * horizon:
                break
            idx = rows[start:stop]
            tt = t[idx] - t[idx[0]]
            n += 1
            hold.append(float(np.sqrt(np.mean((X[idx, 1] - X[idx[0], 1]) ** 2))))
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    sim = model.simulate(X[idx[0], :4], tt, tau[idx])
                if not np.all(np.isfinite(sim)):
                    raise FloatingPointError
                errs.append(float(np.sqrt(np.mean((sim[:, 1] - X[idx, 1]) ** 2))))
                xerrs.append(float(np.sqrt(np.mean((sim[:, 0] - X[idx, 0]) ** 2))))
                ok += 1
            except Exception:  # noqa: BLE001 - a learned model may not simulate
                pass
            start = stop

    def med(v):
        return float(np.median(v)) if v else float("nan")

    return med(errs), med(xerrs), ok / max(n, 1), med(hold)
