"""Names and defaults the command line shows before any maths is imported.

``--help`` and option parsing need the method names, the reference policies and
two defaults, but not numpy, scipy or sklearn: those load only inside the
command that fits. ``models.estimators.registry``, ``models.data.references`` and
``models.fit.conditioning`` take their values from here, and a test checks that
``METHOD_NAMES`` is exactly the registry's keys.
"""

from __future__ import annotations

#: The fitting methods by the name used on the command line and in the store.
METHOD_NAMES = ("grey-mlr", "lag-ridge", "mlr", "pca-quadratic", "pls", "ridge")
#: The method ``fit``, ``analyze`` and ``replay`` use when none is named: the strongest
#: procedure whose every choice is nested inside the training runs (lag-ridge held out on
#: fl_thermal: 1.76 / 2.57 / 2.33 µm on ch1 / ch3 / ch5, against mlr's 6.86 / 6.28 / 6.75).
#: The papers' methods stay available by name.
DEFAULT_METHOD = "lag-ridge"
#: ``replay``'s base when none is named: the declared model as ``fit`` fits it (with
#: lag-ridge, 1.24 / 1.15 / 1.88 µm at one probe an hour against the lagged mlr base's
#: 1.68 / 1.51 / 1.92).
DEFAULT_REPLAY_BASE = "declared"
#: Where rises are measured from (see models/data/references.py).
POLICIES = ("auto", "run-start", "recording-start")
#: A stated accuracy of the transmitters' sensors when none is configured: a
#: class-A Pt100 is ±(0.15 + 0.002·|T|) °C, a transmitter and its wiring add as much.
DEFAULT_SENSOR_ACCURACY_C = 0.5
#: Largest compensation error one sensor off by its accuracy may cause before
#: ``fit`` warns (and, by default, the runtime refuses the model), µm: a fifth
#: of the default ±50 µm clamp, several times a good model's held-out RMSE.
DEFAULT_MAX_BIAS_ERROR_UM = 10.0
