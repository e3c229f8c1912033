"""Write the 0.1.0 model files and their predictions used by tests/test_io.py.

Run with lagsindy 0.1.0 on the path (``git worktree add /tmp/v010 9a45418``;
``PYTHONPATH=/tmp/v010 python tests/data/models_0_1/make.py``). The files record
what 0.1.0 wrote and predicted, so later versions can prove they load them
identically.
"""

import json
from pathlib import Path

import numpy as np

import lagsindy
from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum

HERE = Path(__file__).resolve().parent


def cases():
    sp_ = single_pendulum()
    forced = make_dataset(sp_, n_trajectories=3, duration=2.0, random_state=0)
    passive = make_dataset(
        sp_, n_trajectories=3, duration=2.0, excitation=None, random_state=1
    )
    cart = make_dataset(cart_pendulum(), n_trajectories=3, duration=2.0, random_state=2)
    lib = sp_.paper_library()
    yield "forces", LagrangianSINDy(lib), forced.X, forced.tau
    yield "forces_1d", LagrangianSINDy(lib), forced.X, forced.tau[:, 0]
    yield "fixed_term", LagrangianSINDy(lib, fixed_term="theta_dot**2"), passive.X, None
    yield "fixed_mass", LagrangianSINDy(lib, fixed_term="mass"), passive.X, None
    diss = DissipationLibrary(kinds=("viscous", "coulomb"), eps=0.05)
    clib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=3)
    yield "cart_dissipation", LagrangianSINDy(clib, dissipation=diss), cart.X, cart.tau


def main():
    index = {"lagsindy_version": lagsindy.__version__, "models": {}}
    for name, est, X, tau in cases():
        est.fit(X, tau)
        est.save(HERE / f"{name}.json")
        rows = np.linspace(0, len(X) - 1, 25).astype(int)
        entry = {
            "X": X[rows].tolist(),
            "predict": np.asarray(est.predict(X[rows])).tolist(),
            "equation": est.equation(),
        }
        if tau is not None:
            t = np.asarray(tau)[rows]
            entry["tau"] = t.tolist()
            acc = est.predict_acceleration(X[rows], t if t.ndim == 2 else t[:, None])
        else:
            acc = est.predict_acceleration(X[rows])
        entry["predict_acceleration"] = np.asarray(acc).tolist()
        index["models"][name] = entry
    (HERE / "predictions.json").write_text(json.dumps(index))


if __name__ == "__main__":
    main()
