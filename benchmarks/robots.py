"""Robot arms: LagrangianSINDy on a URDF library, and the classical fit, vs pinocchio.

The targets the robot-arm estimator must reach (issue #42), measured on the simulated
data of :mod:`benchmarks.robots_data` (7-joint arm, 1 kHz, 1e-4 rad position noise,
1 % torque noise, undeclared armature, friction, offsets and a spring on joint 4):

1. the same classical pipeline twice, on the same data: positions and torques
   low-pass filtered alike (Butterworth, zero phase), velocities and accelerations by
   central differences; the regressor of the base parameters (link inertias and
   rotor inertias, :func:`lagsindy.robots.base_parameters`) plus viscous, Coulomb and
   offset columns per joint; ordinary least squares on the first 70 % of the record;
   torque R^2 per joint on the last 30 %. Once with lagsindy's regressor
   (:class:`lagsindy.robots.RobotLibrary`, Newton-Euler recursion in torch), once with
   pinocchio's ``computeJointTorqueRegressor`` (a Python loop over samples);
2. the true model's R^2 on the same filtered held-out data (the ceiling), and the fit
   with the spring's column added (what a diagnosis should find);
3. the cost of the regressor per sample, of the Euler-Lagrange columns of the term
   function through ``torch.func``, and the physically consistent parameters and
   URDF write-back of the identified base parameters;
4. the two-link arm with a relative elbow and gear friction above its inertia.

    python -m benchmarks.robots            # results/robots.md
    python -m benchmarks.robots --quick    # shorter record: results/robots_quick.md
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from . import _common
from ._common import header, write

CUTOFF_HZ = 20.0
EDGE = 500  # samples dropped at each end after filtering (filtfilt's transients)


def _tiny() -> bool:
    return os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")


def filtered_states(t, q, tau, cutoff=CUTOFF_HZ):
    """Zero-phase low-pass of q and tau alike; qd, qdd by central differences."""
    from scipy.signal import butter, filtfilt

    rate = 1.0 / (t[1] - t[0])
    b, a = butter(4, cutoff / (0.5 * rate))
    qf = np.ascontiguousarray(filtfilt(b, a, q, axis=0))
    tauf = np.ascontiguousarray(filtfilt(b, a, tau, axis=0))
    qd = np.gradient(qf, t, axis=0)
    qdd = np.gradient(qd, t, axis=0)
    return qf, qd, qdd, tauf


def friction_columns(qd):
    """Viscous, Coulomb and offset columns per joint: (n, n_dof, 3 n_dof)."""
    n, d = qd.shape
    eye = np.eye(d)
    return np.concatenate(
        [
            qd[:, :, None] * eye,
            np.sign(qd)[:, :, None] * eye,
            np.broadcast_to(eye, (n, d, d)),
        ],
        axis=2,
    )


def r2_per_joint(y, pred):
    return 1.0 - ((y - pred) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)


def lstsq(cols, tau):
    n, d, p = cols.shape
    coef, *_ = np.linalg.lstsq(cols.reshape(n * d, p), tau.reshape(n * d), rcond=None)
    return coef


def pinocchio_columns(lib, q, qd, qdd):
    """pinocchio's regressor (link parameters) + armature columns, lagsindy's order."""
    import pinocchio as pin

    tree = lib.tree_
    model = pin.buildModelFromUrdf(str(tree.path))
    if tree.locked:
        q0 = pin.neutral(model)
        for name, value in tree.locked.items():
            q0[model.joints[model.getJointId(name)].idx_q] = value
        model = pin.buildReducedModel(
            model, [model.getJointId(n) for n in tree.locked], q0
        )
    data = model.createData()
    idx = [model.joints[model.getJointId(c)].idx_v for c in tree.coordinates]
    cols = np.concatenate(
        [10 * (model.getJointId(b.joint) - 1) + np.arange(10) for b in tree.bodies]
    )
    out = np.empty((q.shape[0], len(idx), len(cols)))
    qp, vp, ap = np.zeros(model.nq), np.zeros(model.nv), np.zeros(model.nv)
    for s in range(q.shape[0]):
        qp[idx], vp[idx], ap[idx] = q[s], qd[s], qdd[s]
        out[s] = pin.computeJointTorqueRegressor(model, data, qp, vp, ap)[idx][:, cols]
    return np.concatenate([out, qdd[:, :, None] * np.eye(len(idx))], axis=2)


class _clock:
    """Wall-clock and process CPU seconds of a block (the machine may be shared: CPU
    time is what the work itself cost)."""

    def __enter__(self):
        self.w0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.w0
        self.cpu = time.process_time() - self.c0


def _fit(name, cols_fn, lib, base, split, states, tauf, extra=None):
    q, qd, qdd = states
    cols_fn(q[:8], qd[:8], qdd[:8])  # warm-up: first-call costs are not the method's
    with _clock() as reg:
        full = cols_fn(q, qd, qdd)
    cols = np.concatenate([base.columns(full), friction_columns(qd)], axis=2)
    if extra is not None:
        cols = np.concatenate([cols, extra], axis=2)
    with _clock() as ls:
        coef = lstsq(cols[:split], tauf[:split])
    pred = np.einsum("ndp,p->nd", cols[split:], coef)
    return dict(
        name=name,
        coef=coef,
        r2=r2_per_joint(tauf[split:], pred),
        t_reg=reg,
        t_ls=ls,
        n_base=base.n_base,
    )


def seven_joint(duration, el_samples):
    import torch

    from lagsindy import CandidateLibrary
    from lagsindy.robots import (
        base_parameters,
        consistent_parameters,
        euler_lagrange_columns,
        to_urdf,
    )

    from .robots_data import seven_joint_arm

    torch.set_num_threads(int(os.environ.get("LAGSINDY_BENCH_THREADS", "2")))
    t0 = time.perf_counter()
    data = seven_joint_arm(duration=duration)
    t_sim = time.perf_counter() - t0
    lib = CandidateLibrary.from_urdf(data.urdf, data.joints, locked=data.locked)
    base = base_parameters(lib)
    q, qd, qdd, tauf = (
        x[EDGE:-EDGE] for x in filtered_states(data.t, data.q, data.tau)
    )
    n = q.shape[0]
    split = int(0.7 * n)
    d = q.shape[1]
    ours_fn = lambda a, b, c: lib.euler_lagrange_columns(a, b, c)  # noqa: E731
    pin_fn = lambda a, b, c: pinocchio_columns(lib, a, b, c)  # noqa: E731
    ours = _fit("lagsindy regressor", ours_fn, lib, base, split, (q, qd, qdd), tauf)
    theirs = _fit("pinocchio regressor", pin_fn, lib, base, split, (q, qd, qdd), tauf)
    j, k_true, rest = data.spring
    spring_col = np.zeros((n, d, 1))
    spring_col[:, j, 0] = q[:, j]
    with_spring = _fit(
        "lagsindy + spring column",
        ours_fn,
        lib,
        base,
        split,
        (q, qd, qdd),
        tauf,
        spring_col,
    )
    est_fit = estimator_fit(data, lib, (q, qd, qdd), tauf, split, spring=True)
    est_plain = estimator_fit(data, lib, (q, qd, qdd), tauf, split, spring=False)
    diag = diagnosis(est_plain["est"], (q, qd, qdd), tauf, split)
    # the true model at the same filtered states
    truth = lib.nominal_.copy()
    truth[-d:] = data.armature
    full = lib.euler_lagrange_columns(q[split:], qd[split:], qdd[split:])
    true_tau = (
        full @ truth
        + friction_columns(qd[split:]) @ np.r_[data.viscous, data.coulomb, data.offset]
    )
    true_tau[:, j] += k_true * (q[split:, j] - rest)
    r2_true = r2_per_joint(tauf[split:], true_tau)
    nb = base.n_base
    visc_err = {
        r["name"]: np.abs(r["coef"][nb : nb + d] / data.viscous - 1)
        for r in (ours, theirs, with_spring)
    }
    # cost of the term function and of its torch.func Euler-Lagrange columns
    terms = lib.torch_terms()
    qt, qdt, qddt = (torch.as_tensor(x[:el_samples]) for x in (q, qd, qdd))
    euler_lagrange_columns(terms.fn, qt[:4], qdt[:4], qddt[:4])  # warm-up
    with _clock() as t_fn:
        terms.fn_batch(qt, qdt)
    with _clock() as t_el:
        euler_lagrange_columns(terms.fn, qt, qdt, qddt)
    # consistent parameters for the identified base parameters, and the write-back
    beta = with_spring["coef"][:nb]
    with _quiet(), _clock() as t_cons:
        cons = consistent_parameters(
            lib, base, beta, max_iter=200 if _tiny() else 20000
        )
    with tempfile.TemporaryDirectory() as tmp:  # consistent even when not success
        path = to_urdf(
            lib,
            cons.parameters,
            os.path.join(tmp, "arm7_identified.urdf"),
            damping=with_spring["coef"][nb : nb + d],
            friction=with_spring["coef"][nb + d : nb + 2 * d],
        )
        back = CandidateLibrary.from_urdf(path, data.joints, locked=data.locked)
        round_trip = float(
            np.abs(back.nominal_[: 10 * 7] - cons.parameters[: 10 * 7]).max()
        )
    return dict(
        est_fit=est_fit,
        est_plain=est_plain,
        diag=diag,
        data=data,
        n=n,
        split=split,
        base=base,
        ours=ours,
        theirs=theirs,
        with_spring=with_spring,
        r2_true=r2_true,
        visc_err=visc_err,
        t_sim=t_sim,
        t_fn=t_fn,
        t_el=t_el,
        el_samples=el_samples,
        cons=cons,
        t_cons=t_cons,
        round_trip=round_trip,
        n_terms=len(lib),
    )


def estimator_fit(data, lib, states, tauf, split, spring):
    """``LagrangianSINDy`` on the training part: the URDF library (base parameters,
    physically consistent by default), viscous, Coulomb and offset friction per joint
    (and the spring kind with ``spring``), strong form; held-out R^2 per joint."""
    from lagsindy import DissipationLibrary, LagrangianSINDy
    from lagsindy.robots import FRICTION_KINDS, feasibility

    q, qd, qdd = states
    X = np.hstack([q, qd, qdd])
    kinds = list(FRICTION_KINDS) + (["spring"] if spring else [])
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(kinds), formulation="strong"
    )
    with _quiet() as caught, _clock() as clock:
        est.fit(X[:split], tauf[:split])
    pred = est.predict(X[split:])
    names = [t.name for t in est.dissipation_terms_]
    visc = np.array(
        [est.dissipation_coef_[names.index(f"viscous({j})")] for j in data.joints]
    )
    pi = est.library_.link_parameters(est.coef_)
    return dict(
        est=est,
        r2=r2_per_joint(tauf[split:], pred),
        visc_err=np.abs(visc / data.viscous - 1),
        clock=clock,
        min_eig=float(feasibility(pi, 7).min()),
        rotor_min=float(pi[70:].min()),
        warnings=[str(w.message)[:120] for w in caught.caught],
        spring=(
            float(est.dissipation_coef_[names.index("spring(joint4)")])
            if "spring(joint4)" in names
            else None
        ),
    )


def diagnosis(est, states, tauf, split):
    """``diagnose`` on the training part, from the fit without the spring kind."""
    from lagsindy import diagnose
    from lagsindy.robots import ROBOT_CATALOGUE

    X = np.hstack(states)[:split]
    catalogue = [k for k in ROBOT_CATALOGUE if k not in ("delay", "joint_delay")]
    if _tiny():
        catalogue = ["spring"]
    with _quiet(), _clock() as clock:
        report = diagnose(est, X, tauf[:split], catalogue=catalogue)
    return dict(
        clock=clock,
        steps=[
            (s.candidate.name, float(s.coefficient))
            for s in report.steps
            if s.how != "start"  # the fitted model's own terms, refitted
        ],
    )


class _quiet:
    def __enter__(self):
        import warnings

        self._w = warnings.catch_warnings(record=True)
        self.caught = self._w.__enter__()
        warnings.simplefilter("always")
        return self

    def __exit__(self, *exc):
        return self._w.__exit__(*exc)


def planar(duration):
    from lagsindy import CandidateLibrary
    from lagsindy.robots import base_parameters

    from .robots_data import planar_arm

    data = planar_arm(duration=duration)
    lib = CandidateLibrary.from_urdf(data.urdf)
    base = base_parameters(lib)
    q, qd, qdd, tauf = (
        x[EDGE:-EDGE] for x in filtered_states(data.t, data.q, data.tau)
    )
    split = int(0.7 * q.shape[0])
    fn = lambda a, b, c: lib.euler_lagrange_columns(a, b, c)  # noqa: E731
    fit = _fit("lagsindy regressor", fn, lib, base, split, (q, qd, qdd), tauf)
    nb, d = base.n_base, 2
    friction = data.viscous * data.qd_true + data.coulomb * np.sign(data.qd_true)
    inertial = data.tau_true - friction - data.offset
    return dict(
        fit=fit,
        visc=fit["coef"][nb : nb + d] / data.viscous - 1,
        coul=fit["coef"][nb + d : nb + 2 * d] / data.coulomb - 1,
        rms_friction=np.sqrt((friction**2).mean(0)),
        rms_rigid=np.sqrt((inertial**2).mean(0)),
        labels=base.labels,
    )


def _trow(label, clock):
    return f"| {label} | {clock.wall:.3f} | {clock.cpu:.3f} |"


def _row(label, values, fmt="{:.4f}"):
    return f"| {label} | " + " | ".join(fmt.format(v) for v in values) + " |"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="short record: results/robots_quick.md"
    )
    args = parser.parse_args(argv)
    import pinocchio  # noqa: F401  (ImportError: the runner skips this benchmark)

    if _tiny():
        duration, el_samples, planar_duration = 3.0, 20, 3.0
    elif args.quick:
        duration, el_samples, planar_duration = 10.0, 2000, 10.0
    else:
        # 70 % of (29.6 s - 2 x 0.5 s) at 1 kHz: 20,020 training samples; the
        # torch.func columns measured on 2000 samples (minutes for 20,000)
        duration, el_samples, planar_duration = 29.6, 2000, 20.0
    res = seven_joint(duration, el_samples)
    pl = planar(planar_duration)
    d = 7
    n_train = res["split"]
    frac = n_train / res["n"]
    fit_cpu = res["ours"]["t_reg"].cpu * frac + res["ours"]["t_ls"].cpu
    fit_wall = res["ours"]["t_reg"].wall * frac + res["ours"]["t_ls"].wall
    lines = [
        header(
            "Robot arms: LagrangianSINDy on a URDF library vs the classical base-parameter fit",
            _common.command("robots", argv),
        ).rstrip()
    ]
    lines += [
        "",
        f"Data: `benchmarks/robots_data.py`, 7-joint arm `tests/robots/data/arm7.urdf` "
        f"(the Panda's kinematic layout, inertias of our own; fingers locked), "
        f"{res['n'] + 2 * EDGE} samples at 1 kHz ({EDGE} dropped at each end after filtering), exciting Fourier trajectories (5 harmonics, 10 s "
        f"period) inside the joint limits; undeclared armature, viscous and Coulomb "
        f"friction, offsets, and a spring on joint 4 (4 N m/rad); noise 1e-4 rad on q, "
        f"1 % of each joint's torque RMS on tau. First 70 % ({n_train} samples) to fit, "
        f"last 30 % held out. Positions and torques filtered alike (Butterworth 4th "
        f"order, {CUTOFF_HZ:.0f} Hz, zero phase), derivatives by central differences. "
        f"{res['n_terms']} parameters (70 link + 7 rotor) -> {res['base'].n_base} base "
        f"parameters, + 21 friction columns.",
        "",
        "## Held-out torque R^2 per joint",
        "",
        "| model | " + " | ".join(f"joint {i}" for i in range(1, d + 1)) + " |",
        "|---|" + "---|" * d,
        _row("true model (ceiling)", res["r2_true"]),
        _row("lagsindy regressor: base + friction", res["ours"]["r2"]),
        _row("pinocchio regressor: base + friction", res["theirs"]["r2"]),
        _row("lagsindy: base + friction + spring column", res["with_spring"]["r2"]),
        _row(
            "LagrangianSINDy: URDF library + friction (consistent)",
            res["est_plain"]["r2"],
        ),
        _row(
            "LagrangianSINDy: URDF library + friction + spring kind (consistent)",
            res["est_fit"]["r2"],
        ),
        "",
        "Largest |R^2 - true model's| over the joints: "
        f"{np.abs(res['ours']['r2'] - res['r2_true']).max():.4f} (without the spring), "
        f"{np.abs(res['with_spring']['r2'] - res['r2_true']).max():.4f} (with it); "
        "acceptance: 0.005 on every joint. The two regressors' fits agree to "
        f"{np.abs(res['ours']['r2'] - res['theirs']['r2']).max():.1e} in R^2.",
        "",
        "## Viscous friction, relative error per joint",
        "",
        "| model | " + " | ".join(f"joint {i}" for i in range(1, d + 1)) + " |",
        "|---|" + "---|" * d,
    ]
    for name, err in res["visc_err"].items():
        lines.append(_row(name, 100 * err, "{:.1f} %"))
    ef, ep, dg = res["est_fit"], res["est_plain"], res["diag"]
    lines.append(
        _row("LagrangianSINDy + spring kind", 100 * ef["visc_err"], "{:.1f} %")
    )
    found = ", ".join(f"{t} = {c:.3f}" for t, c in dg["steps"]) or "nothing"
    pin_cpu = res["theirs"]["t_reg"].cpu * frac + res["theirs"]["t_ls"].cpu
    pin_wall = res["theirs"]["t_reg"].wall * frac + res["theirs"]["t_ls"].wall
    lines += [
        "",
        "## LagrangianSINDy on the URDF library",
        "",
        f"`LagrangianSINDy(CandidateLibrary.from_urdf(...), dissipation="
        f'DissipationLibrary(["viscous", "coulomb", "bias", "spring"]), '
        f'formulation="strong")` on the {n_train} training samples: '
        f"{res['base'].n_base} base parameters (unpenalized) + 28 dissipation "
        "candidates (sparse), physically consistent by default. "
        f"Held-out R^2 minus the true model's, worst joint: "
        f"{(ef['r2'] - res['r2_true']).min():+.4f} (acceptance: -0.005); viscous "
        f"friction within {100 * ef['visc_err'].max():.1f} % on every joint "
        f"(acceptance: 10 %); spring(joint4) = {ef['spring']:.3f} N m/rad (true "
        f"{res['data'].spring[1]:.1f}); smallest pseudo-inertia eigenvalue of the "
        f"link parameters {ef['min_eig']:.2e}, smallest rotor inertia "
        f"{ef['rotor_min']:.2e} (feasible: >= 0).",
        "",
        f"Without the spring kind (viscous, Coulomb, offsets only), "
        f'`diagnose(est, X, tau, catalogue=["viscous", "coulomb", "bias", '
        f'"spring"])` on the training part adds: {found} '
        f"({dg['clock'].cpu:.1f} s CPU, {dg['clock'].wall:.1f} s wall).",
        "",
        "| fit, same data and process | wall s | CPU s |",
        "|---|---|---|",
        _trow("LagrangianSINDy fit (+ spring kind), whole `fit`", ef["clock"]),
        _trow("LagrangianSINDy fit (friction only), whole `fit`", ep["clock"]),
        f"| pinocchio regressor + least squares (training part) | {pin_wall:.3f} | "
        f"{pin_cpu:.3f} |",
        "",
        f"The fit's CPU time is {ef['clock'].cpu / pin_cpu:.1f} times the classical "
        f"pipeline's; {'within' if ef['clock'].cpu <= 10 else 'ABOVE'} the issue's "
        "10 s target in CPU time (wall-clock time is the shared machine's: see the "
        "load average below).",
    ]
    cons = res["cons"]
    lines += [
        "",
        "## Time (this run, same process and data)",
        "",
        "Wall-clock and CPU seconds of this process (the machine was shared: CPU time is "
        "what the work cost; load average over the last 5 minutes at the end of the run: "
        f"{os.getloadavg()[1]:.1f} on {os.cpu_count()} cores).",
        "",
        "| step | wall s | CPU s |",
        "|---|---|---|",
        _trow(
            f"lagsindy regressor, {res['n']} samples (Newton-Euler in torch)",
            res["ours"]["t_reg"],
        ),
        _trow(
            f"pinocchio regressor, {res['n']} samples (Python loop over samples)",
            res["theirs"]["t_reg"],
        ),
        _trow(
            f"least squares, {n_train} x 7 rows, {res['base'].n_base + 21} columns",
            res["ours"]["t_ls"],
        ),
        _trow(f"term function `fn_batch`, {res['el_samples']} samples", res["t_fn"]),
        _trow(
            f"Euler-Lagrange columns by torch.func (`euler_lagrange_columns`), {res['el_samples']} samples",
            res["t_el"],
        ),
        _trow("consistent parameters (Dykstra projection)", res["t_cons"]),
        f"| simulating the data with pinocchio | {res['t_sim']:.2f} | |",
        "",
        f"Per sample (CPU): regressor {1e6 * res['ours']['t_reg'].cpu / res['n']:.1f} us (lagsindy) vs "
        f"{1e6 * res['theirs']['t_reg'].cpu / res['n']:.1f} us (pinocchio + Python loop); "
        f"term values {1e6 * res['t_fn'].cpu / res['el_samples']:.1f} us; torch.func columns "
        f"{1e6 * res['t_el'].cpu / res['el_samples']:.0f} us. "
        f"Fit on the training part ({n_train} samples): regressor + least squares "
        f"{fit_cpu:.2f} s CPU ({fit_wall:.2f} s wall), "
        f"{'within' if fit_cpu <= 10 else 'ABOVE'} the issue's 10 s target in CPU "
        "time (the wall-clock time is the shared machine's); "
        f"through torch.func the columns alone would take about "
        f"{res['t_el'].cpu * 20000 / res['el_samples']:.0f} s CPU for 20,000 samples "
        f"(measured on {res['el_samples']}), so the evaluator should use `RobotTerms.columns` "
        "(the recursion) for URDF libraries.",
        "",
        "## Identified parameters back to a URDF",
        "",
        f"Consistent parameters for the identified base parameters (fit with the spring): "
        f"{'found' if cons.success else 'NOT found'}; smallest pseudo-inertia eigenvalue "
        f"{cons.min_eigenvalue.min():.2e}; base parameters reproduced to {cons.violation:.1e} "
        f"(relative). Written with `to_urdf` and read back: link parameters equal to "
        f"{res['round_trip']:.1e}.",
        "",
        "## Two-link arm, relative elbow, gear friction above the rigid-body torques",
        "",
        f"RMS torque per joint: friction {pl['rms_friction'][0]:.2f}, {pl['rms_friction'][1]:.2f} N m; "
        f"rigid body (inertia + gravity) {pl['rms_rigid'][0]:.2f}, {pl['rms_rigid'][1]:.2f} N m. "
        f"Base parameters: {'; '.join(pl['labels'])}.",
        "",
        "| | joint 1 | joint 2 |",
        "|---|---|---|",
        _row("held-out R^2", pl["fit"]["r2"]),
        _row("viscous error", 100 * pl["visc"], "{:.2f} %"),
        _row("Coulomb error", 100 * pl["coul"], "{:.2f} %"),
        "",
    ]
    name = "robots_quick.md" if (args.quick or _tiny()) else "robots.md"
    write(name, "\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
