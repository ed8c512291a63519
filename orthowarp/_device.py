"""Device selection shared by everything that launches kernels."""

import warp as wp

from .errors import DeviceError


def resolve_device(device=None):
    """Return a Warp device: ``None`` picks the first CUDA device if any, else the CPU.

    Parameters
    ----------
    device : str or warp.context.Device, optional
        ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a Warp device.
    """
    if device is None:
        return wp.get_device("cuda:0") if wp.get_cuda_device_count() > 0 else wp.get_device("cpu")
    try:
        return wp.get_device(device)
    except Exception as e:  # Warp raises plain exceptions for unknown aliases
        raise DeviceError(f"Unknown or unavailable Warp device {device!r}: {e}") from e
