"""``lagsindy simulate`` and ``simulate-model``: data sets and rollouts as CSV.

Options, the system's name, the output path and the initial states are checked
before the simulation code loads (:mod:`._checks`).
"""

from __future__ import annotations

import numpy as np

from . import _checks
from ._checks import CLIError, split, state_names
from ._io import _check_out, _load, _say, _write_csv


def _simulate(args) -> int:
    if args.model is not None:
        if args.system is not None:
            raise CLIError("give either --system or --model, not both")
        if not args.x0:
            raise CLIError("simulating a saved model needs --x0 (the initial state)")
        return _simulate_model(args)
    if args.system is None:
        raise CLIError(
            "give --system NAME (a built-in system) or --model FILE (a saved model)"
        )
    name = _checks.system_name(args.system)
    if args.trajectories < 1:
        raise CLIError("--trajectories must be at least 1")
    if not (args.duration > 0 and args.rate > 0 and args.noise >= 0):
        raise CLIError("--duration and --rate must be positive, --noise >= 0")
    _check_out(args.out)
    from ..systems import get_system, make_dataset

    system = get_system(name)
    excitation = None if args.passive else args.excitation
    data = make_dataset(
        system,
        n_trajectories=args.trajectories,
        duration=args.duration,
        rate=args.rate,
        excitation=excitation,
        noise=args.noise,
        protocol=args.protocol,
        random_state=args.seed,
    )
    df = data.to_frame()
    if args.positions_only:
        keep = ["trajectory", "t", *system.coordinates]
        keep += [c for c in df.columns if c.startswith("tau_")]
        df = df[keep]
    _write_csv(df, args.out)
    _say(
        args,
        f"wrote {args.out}: {system.name}, {args.trajectories} trajectories x "
        f"{args.duration:g} s at {args.rate:g} Hz ({len(df)} rows), "
        f"{'passive' if excitation is None else f'input {excitation!r}'}, noise "
        f"sigma={args.noise} ({args.protocol} protocol); "
        f"columns: {', '.join(df.columns)}",
    )
    return 0


def _simulate_model(args) -> int:
    _check_out(args.out)
    coords, _ = _checks.peek_model(args.model)
    x0 = []
    for text in args.x0:
        try:
            values = [float(v) for v in split(text)]
        except ValueError:
            raise CLIError(
                f"--x0 {text!r} is not a comma-separated list of numbers"
            ) from None
        if coords is not None and len(values) != 2 * len(coords):
            raise CLIError(
                f"--x0 {text!r} has {len(values)} value(s); the model's state "
                f"{state_names(coords, accelerations=False)} has {2 * len(coords)}"
            )
        if not np.all(np.isfinite(values)):
            raise CLIError(f"--x0 {text!r} contains NaN or infinite values")
        x0.append(values)
    if args.duration <= 0 or args.rate <= 0:
        raise CLIError("--duration and --rate must be positive")
    import pandas as pd

    est = _load(args.model)
    n = est.n_dof_
    for text, values in zip(args.x0, x0):
        if len(values) != 2 * n:
            raise CLIError(
                f"--x0 {text!r} has {len(values)} value(s); the model's state "
                f"{state_names(est.coordinates_, accelerations=False)} has {2 * n}"
            )
    t = np.arange(int(round(args.duration * args.rate)) + 1) / args.rate
    frames = []
    for k, start in enumerate(x0):
        states = est.simulate(np.asarray(start), t)
        X = est.model_.trajectory_to_X(states)
        frame = pd.DataFrame(X, columns=state_names(est.coordinates_))
        frame.insert(0, "t", t)
        frame.insert(0, "trajectory", k)
        frames.append(frame)
    df = pd.concat(frames, ignore_index=True)
    _write_csv(df, args.out)
    _say(
        args,
        f"wrote {args.out}: {len(x0)} trajectory(ies) x {t[-1]:g} s of "
        f"{est.equation(4)} (unforced)",
    )
    return 0
