"""Receding-horizon control (eq. 30) solved on-line by C/GMRES (Ohtsuka 2004), compiled; its
plain-NumPy twin is a test oracle, ``tests/support/rhc_reference.py``."""
