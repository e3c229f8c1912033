"""The only numpy <-> torch boundary of the package."""

from __future__ import annotations

import numpy as np
import torch

_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def resolve_dtype(dtype) -> torch.dtype:
    """Map ``"float64"``/``"float32"`` (or a torch dtype) to a torch dtype."""
    if isinstance(dtype, torch.dtype):
        return dtype
    try:
        return _DTYPES[str(dtype)]
    except KeyError:
        raise ValueError(
            f"dtype must be one of {sorted(_DTYPES)}, got {dtype!r}"
        ) from None


def resolve_device(device) -> torch.device:
    """Return a torch device; ``"cuda"`` without a GPU raises a clear ``ValueError``."""
    try:
        dev = torch.device(device if device is not None else "cpu")
    except (RuntimeError, TypeError) as exc:
        raise ValueError(
            f"device={device!r} is not a torch device ({exc}); use 'cpu' or 'cuda'"
        ) from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"device={device!r} was requested but torch.cuda.is_available() is False; "
            "use device='cpu'"
        )
    return dev


def to_tensor(array, *, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """Convert an array-like to a tensor of the given dtype on the given device."""
    if torch.is_tensor(array):
        return array.to(dtype=dtype, device=device)
    arr = np.asarray(array)
    if not arr.flags.writeable or any(st < 0 for st in arr.strides):
        # torch wraps neither read-only memory (e.g. pandas views) nor negative
        # strides (reversed views such as tau[:, ::-1])
        arr = arr.copy()
    return torch.as_tensor(arr, dtype=dtype, device=device)


def to_numpy(tensor) -> np.ndarray:
    """Detach a tensor to a float64 numpy array on the CPU."""
    if torch.is_tensor(tensor):
        return tensor.detach().to("cpu", torch.float64).numpy()
    return np.asarray(tensor, dtype=np.float64)
