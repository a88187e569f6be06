"""skelid: identify the non-linear joint of a vibration test rig (clearance, contact
stiffness, viscous and dry friction) with the skeleton methods, and diagnose why a
simulation does not match the measurement.

The same core as the ``skelid`` command line, called on numpy arrays:

- :func:`track` - instantaneous envelope, frequency and phase (wavelet ridge or Hilbert);
- :func:`identify` - the joint's parameters with their standard errors, and the skeleton;
- :func:`gap` - the sim-to-real gap of one run against a rig model, and its verdict;
- :func:`read_campaign` - the runs of a campaign archive.

Errors are :class:`SkelidError`, with the library's messages.
"""

from ._skelid import SkelidError, __version__, gap, identify, read_campaign, track

__all__ = ["SkelidError", "__version__", "gap", "identify", "read_campaign", "track"]
