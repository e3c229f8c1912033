"""Benchmark systems of the paper (and more), and reproducible data sets."""

from .base import COULOMB_EPS, System
from .cart_pendulum import cart_pendulum
from .dataset import PROTOCOLS, Dataset, make_dataset
from .double_pendulum import double_pendulum
from .elastic_pendulum import elastic_pendulum
from .planar_chain import chain_lagrangian, planar_chain
from .single_pendulum import single_pendulum
from .spherical_pendulum import spherical_pendulum
from .spring_chain import spring_chain
from .triple_pendulum import (
    multiarm_triple_pendulum,
    n_link_lagrangian,
    triple_pendulum,
)

PAPER_SYSTEMS = {
    "single_pendulum": single_pendulum,
    "cart_pendulum": cart_pendulum,
    "double_pendulum": double_pendulum,
    "spherical_pendulum": spherical_pendulum,
}
SYSTEMS = {
    **PAPER_SYSTEMS,
    "triple_pendulum": triple_pendulum,
    "planar_chain": planar_chain,
    "spring_chain": spring_chain,
    "elastic_pendulum": elastic_pendulum,
}


def get_system(name: str) -> System:
    """A system by name (``"cart_pendulum"``, ``"cart-pendulum"`` and ``"cart"`` all work)."""
    key = name.strip().lower().replace("-", "_").replace(" ", "_")
    matches = [k for k in SYSTEMS if k == key or k.split("_")[0] == key]
    if len(matches) != 1:
        raise ValueError(f"unknown system {name!r}; available: {sorted(SYSTEMS)}")
    return SYSTEMS[matches[0]]()


__all__ = [
    "COULOMB_EPS",
    "Dataset",
    "PAPER_SYSTEMS",
    "PROTOCOLS",
    "SYSTEMS",
    "System",
    "cart_pendulum",
    "chain_lagrangian",
    "double_pendulum",
    "elastic_pendulum",
    "get_system",
    "make_dataset",
    "multiarm_triple_pendulum",
    "n_link_lagrangian",
    "planar_chain",
    "single_pendulum",
    "spherical_pendulum",
    "spring_chain",
    "triple_pendulum",
]
