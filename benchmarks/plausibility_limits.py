"""What the plausibility check can see, per sensor, on the simulated machine; prints JSON.

Fits the demo's training data (six programmes, seed 1), then for each sensor:
the σ its residual is judged by with every other sensor good, the smallest
offset flagged (``plausibility_sigma`` · σ, °C), the whole-run MLR model's
coefficient (µm/°C) and so the most compensation error a fault can cause
before it is flagged (µm). Then the largest |z| of sound sensors on unseen
programmes (recorded offline at 30 s, two seeds each), with every sensor good
and with each one left out in turn: the margin below the threshold.

Run: ``.venv/bin/python benchmarks/plausibility_limits.py`` (about a minute).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from gateway.demo.compensate import write_training_data
from gateway.limits import PlausibilityLimits
from gateway.live.plausibility import Plausibility
from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.mlr import MlrModel
from models.estimators.sensor_relations import fit_relations
from simulator.params import load_params
from simulator.programs import production_program, program_by_name
from simulator.record import record, write_recording


def main() -> None:
    limits = PlausibilityLimits()
    with tempfile.TemporaryDirectory() as folder:
        training = Path(folder) / "training.csv"
        write_training_data(training, seed=1)
        prepared = prepare(load_runs(training))
        names = prepared.inputs.sensors
        relations = fit_relations(prepared.inputs.rise_C, names, prepared.inputs.run_index)
        check = Plausibility(relations, limits)
        model = MlrModel().fit(prepared.inputs, prepared.error_um)
        per_sensor = {}
        for k, sensor in enumerate(names):
            said = relations.predict(sensor, dict.fromkeys(names, 0.0))
            z_per_C, _ = check.z_score(
                sensor, 1.0 + said.predicted_rise_C, dict.fromkeys(names, 0.0)
            )
            sigma = 1.0 / z_per_C
            coefficient = float(model.coef_um_per_C_[k])
            per_sensor[sensor] = {
                "held_out_sigma_C": round(relations.held_out_sigma_C[sensor], 3),
                "judged_sigma_C": round(sigma, 3),
                "smallest_flagged_C": round(limits.sigma * sigma, 2),
                "model_um_per_C": round(coefficient, 2),
                "error_before_flag_um": round(abs(coefficient) * limits.sigma * sigma, 2),
            }
        margins = {}
        programmes = [program_by_name("const8000"), production_program(47, 10 * 3600.0)]
        for programme in programmes:
            for seed in (5, 11):
                path = Path(folder) / "unseen.csv"
                write_recording(path, record(load_params(), [programme], seed=seed, sample_s=30))
                rises = prepare(load_runs(path)).inputs.rise_C
                worst = 0.0
                for left_out in (None, *names):
                    for row in rises:
                        good = {n: float(v) for n, v in zip(names, row, strict=True)}
                        good.pop(left_out, None)
                        for sensor, value in good.items():
                            others = {o: v for o, v in good.items() if o != sensor}
                            worst = max(worst, abs(check.z_score(sensor, value, others)[0]))
                margins[f"{programme.name} seed {seed} ({rises.shape[0]} samples)"] = round(
                    worst, 2
                )
    print(
        json.dumps(
            {
                "plausibility_sigma": limits.sigma,
                "per_sensor": per_sensor,
                "largest_sound_z_unseen": margins,
            },
            indent=2,
            ensure_ascii=False,
        )
    )


if __name__ == "__main__":
    main()
