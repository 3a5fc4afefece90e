"""Make the workbench's bundled data: the demo and the lessons (run from the repository root).

    python assets/make_assets.py

Every file comes from the engine's simulator (:func:`magcal.simulation.simulate_timeseries`) with effects hidden
by the catalogue's own perturbations (:mod:`magcal.effects`), so the data and the model agree on what each effect
is. Seeds are fixed: running the script again writes the same files.

Outputs (committed):

* ``assets/demo.csv`` - the four-sensor cross of Chi et al. (2017), Table 1 errors, 3 nT noise, 1 500 samples of
  a smooth turn with time and temperature, and a temperature-dependent bias hidden in sensor 2: the base model
  stops above the noise floor, Diagnose points at the temperature, Add brings the error down to the floor.
* ``assets/lessons/<slug>/{data.csv, guide.md, lesson.json}`` - one effect hidden per lesson (one lesson hides
  two); ``lesson.json`` holds the answer, which the workbench shows only when asked.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import magcal
from magcal import io as mio
from magcal.model import EFFECTS, _ensure_catalogue

HERE = Path(__file__).resolve().parent
N_SAMPLES = 1500
FLOAT_FORMAT = "%.8g"  # 0.001 nT at 50 000 nT; well below the 3 nT noise

#: slug -> (order, title, hidden [(effect, sensor 0-based or None, magnitude or None)], guide, explanation)
LESSONS = {
    "warm-sensor": (
        1, "A sensor that feels the heat",
        [("temperature_bias", 1, 2.0)],
        """The array was turned slowly for two and a half minutes while the room warmed and cooled.

1. **Run the chosen method** (Calibrate tab). Compare the total-field RMS with the noise floor: is the base model
   enough?
2. Look at the corrected clouds: is the colour (the residual) spread evenly over the sphere, or do some sensors
   look worse than others? Open the **Model** tab and the evidence plots: against which channel does the residual
   line up?
3. Press **Diagnose**, read the ranked candidates, **Add** the one you believe, and watch the RMS history.
4. **Check my model** when the RMS reaches the floor.""",
        "Sensor 2's bias changes with temperature (about 2 nT/K on its strongest axis). Only that sensor's "
        "residual follows the temperature channel; the fitted beta of the other sensors stays at zero within "
        "its uncertainty.",
    ),
    "slow-drift": (
        2, "Offsets that wander",
        [("bias_drift", None, 300.0)],
        """A long recording. The two-step calibration looks fine at first sight, but is it at the noise floor?

1. Calibrate, then look at the residual against **time** (Model tab, evidence).
2. Is the structure the same in every sensor? Does it depend on where the field points, or only on when?
3. Diagnose, add what you think is missing, and check.""",
        "Every sensor's bias drifts linearly in time (up to 300 nT/h on one axis). The residual against time is "
        "a slow trend that changes sign with the field direction, because the drift is a vector offset.",
    ),
    "bent-response": (
        3, "A response that is not quite linear",
        [("nonlinearity_quadratic", 2, None)],
        """Here time and temperature tell you nothing. Where does the residual live, then?

1. Calibrate and look at the corrected clouds with a large residual exaggeration (View tab): is the pattern on
   the sphere random, or a shape?
2. The diagnosis splits the residual by spherical-harmonic degree over the field direction. Which degree stands
   out, and in which sensor?
3. Add the term you think explains it and check.""",
        "Sensor 3 has a quadratic nonlinearity (y_j += q_j B_j^2, about 20 nT at 50 uT). It shows as power at "
        "spherical-harmonic degree 3 in that sensor only; time and temperature are innocent.",
    ),
    "breathing-field": (
        4, "The Earth moves (a little)",
        [("reference_drift", None, None)],
        """The sensors are fine, the field is not: or is it the other way round?

1. Calibrate. Compare the sensors' residuals against time: do they move together?
2. A sensor error depends on the field direction in that sensor; a change of the field itself does not.
   Which kind of structure do you see?
3. Diagnose, add, check.""",
        "The total field itself varied during the recording (a slow reference drift of about 5 nT, the kind a "
        "magnetic storm or the daily variation gives). All four sensors see it alike, whatever their attitude.",
    ),
    "two-culprits": (
        5, "Two effects at once",
        [("temperature_scale", None, 30.0), ("bias_step", 3, 10.0)],
        """This one hides **two** effects. Adding the first will not bring you to the floor.

1. Calibrate, diagnose, add the top candidate and refit.
2. Diagnose again: is there still structure? Look at the RMS history against the floor line.
3. Keep going until the verdict reads `adequate`, then check.""",
        "Every sensor's scale factors change with temperature (30 ppm/K), and sensor 4's bias jumps by about "
        "10 nT partway through the recording (perming after a field shock). Each is found only once the "
        "other is in the model or out of the way.",
    ),
}

DEMO_HIDDEN = [("temperature_bias", 1, 2.0)]


def perturbations(hidden):
    _ensure_catalogue()
    out = []
    for name, sensor, magnitude in hidden:
        effect = EFFECTS[name](sensor=sensor)
        out.append(effect.perturbation(magnitude, sensor))
    return out


def simulate(hidden, seed):
    return magcal.simulate_timeseries("chi2017", n_samples=N_SAMPLES, seed=seed, perturbations=perturbations(hidden))


def label(name, sensor):
    return name if sensor is None else f"{name}:{sensor + 1}"


def write_demo():
    ds = simulate(DEMO_HIDDEN, seed=2017)
    meta = {"description": "magcal demo: Chi et al. (2017) cross, Table 1 errors, 3 nT noise; one effect hidden "
                           "(the workbench's Diagnose finds it)"}
    mio.write_csv(HERE / "demo.csv", ds.replace(metadata={"simulated": "true"}), metadata=meta,
                  float_format=FLOAT_FORMAT)


def write_lessons():
    root = HERE / "lessons"
    for seed, (slug, (order, title, hidden, guide, explanation)) in enumerate(LESSONS.items(), start=100):
        folder = root / slug
        folder.mkdir(parents=True, exist_ok=True)
        ds = simulate(hidden, seed)
        mio.write_csv(folder / "data.csv", ds.replace(metadata={"simulated": "true"}),
                      metadata={"lesson": slug}, float_format=FLOAT_FORMAT)
        (folder / "guide.md").write_text(guide.strip() + "\n", encoding="utf-8")
        doc = {"title": title, "order": order, "data": "data.csv", "guide": "guide.md",
               "answer": {"effects": [label(n, s) for n, s, _ in hidden], "explanation": explanation},
               "made_by": "assets/make_assets.py", "seed": seed}
        (folder / "lesson.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def main():
    write_demo()
    write_lessons()
    print(f"wrote {HERE / 'demo.csv'} and {len(LESSONS)} lessons under {HERE / 'lessons'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
