"""bmsid: live battery parameter identification for BMS gateways.

Data flow, visible in the package layout::

    canbus/ (frames -> samples)  ->  estimate/ (estimator bank)  ->  publish/ (CAN, MQTT)
                                       ^
                                  model/ (OCV, hysteresis, 2RC simulator, ARX mapping)

Conventions everywhere: SI units (A, V, ohm, F, s), positive current = discharge,
RC branch 1 is the *fast* branch (tau1 < tau2).
"""

__version__ = "0.1.0"
