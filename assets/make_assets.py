"""Make the workbench's bundled data: the demo and the lessons (run from the repository root).

    python assets/make_assets.py

Every file comes from the engine's simulator (:func:`magcal.data.simulation.simulate_timeseries`) with effects hidden
by the catalogue's own perturbations (:mod:`magcal.model.effects`), so the data and the model agree on what each effect
is. Seeds are fixed: running the script again writes the same files.

Outputs (committed):

* ``assets/demo.csv`` - the four-sensor cross of Chi et al. (2017), Table 1 errors, 3 nT noise, 1 500 samples of
  a smooth turn with time and temperature, and a temperature-dependent bias hidden in sensor 2: the base model
  stops above the noise floor, Diagnose points at the temperature, Add brings the error down to the floor.
* ``assets/lessons/<slug>/{data.csv, guide.md, lesson.json}`` - one effect hidden per lesson (one lesson hides
  two); ``lesson.json`` holds the answer, which the workbench shows only when asked.
* ``assets/lessons/cannot-tumble/`` - a simulated vehicle (:func:`magcal.data.vehicle.simulate_vehicle`): full yaw
  turns, roll within +-20 deg and pitch within +-10 deg, a fluxgate mounted with permuted axes and 2 deg off the
  right angle, soft and hard iron, its attitude in ``roll_deg, pitch_deg, yaw_deg``; the field is IGRF at the place
  and date the guide gives (no reference column: the page's location makes it). The total-field fit is
  undetermined there; the vector fit finds the mounting, which is the answer.
* ``assets/lessons/drone-current/`` - a simulated quadcopter (:func:`magcal.data.vehicle.simulate_vehicle`) whose
  compass sees the battery current (the catalogue's ``current_field`` hidden by its own perturbation), with the
  attitude in ``qw..qz``, the field vector in ``ref_n, ref_e, ref_d``, the current in ``current_A`` and the board's
  temperature: the loop on a vehicle (issue 40), judged on the vector model's effects.
* ``assets/lessons/tilted-compass/`` - a simulated board (:func:`magcal.data.board.simulate_board`): a magnetometer
  beside an accelerometer, tumbled by hand with still moments, the magnetometer mounted ``ROLL_180_YAW_90`` and
  2 deg off it; the total-field fit leaves the 2 deg, which the tilt compensation turns into heading; the gravity
  fit finds the mounting, which is the answer (the lesson is judged on the gravity fit: ``"fit": "gravity"``).
* ``assets/lessons/survey-drone-current/`` - a simulated compensation flight
  (:func:`magcal.data.compensation_flight.simulate_compensation_flight`): a survey drone's scalar magnetometer beside
  a fluxgate, flown through the box, with a field per ampere of its battery current that Tolles-Lawson does not
  model; judged on the compensation's terms (``"model": "compensation"``) and its FOM within 1.2x the true one's.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import magcal
from magcal.data import io as mio
from magcal.model.terms import EFFECTS  # the catalogue is registered when magcal is imported

HERE = Path(__file__).resolve().parent
N_SAMPLES = 1500
FLOAT_FORMAT = "%.8g"  # 0.001 nT at 50 000 nT; well below the 3 nT noise

#: slug -> (order, title, hidden [(effect, sensor 0-based or None, magnitude or None)], guide, explanation)
LESSONS = {
    "warm-sensor": (
        1,
        "A sensor that feels the heat",
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
        2,
        "Offsets that wander",
        [("bias_drift", None, 300.0)],
        """A long recording. The two-step calibration looks fine at first sight, but is it at the noise floor?

1. Calibrate, then look at the residual against **time** (Model tab, evidence).
2. Is the structure the same in every sensor? Does it depend on where the field points, or only on when?
3. Diagnose, add what you think is missing, and check.""",
        "Every sensor's bias drifts linearly in time (up to 300 nT/h on one axis). The residual against time is "
        "a slow trend that changes sign with the field direction, because the drift is a vector offset.",
    ),
    "bent-response": (
        3,
        "A response that is not quite linear",
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
        4,
        "The Earth moves (a little)",
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
        5,
        "Two effects at once",
        [("temperature_scale", None, 30.0), ("bias_step", 3, 10.0)],
        """This one hides **two** effects. Adding the first will not bring you to the floor.

1. Calibrate, diagnose, add the top candidate and refit.
2. Diagnose again: is there still structure? Look at the RMS history against the floor line.
3. Watch it happen: in the View tab's *Time window*, tick *Show a time window*, set the width to 10 % and press
   *Play*. The sphere shows only the samples of the moving window (a black dot and line: each sensor's current
   direction), and the evidence plot's time panel shades the same window. Look at sensor 4's corrected cloud:
   before about 60 % of the recording (90 s) one side of its sphere is blue and the other red; after it the colours
   flip and stay flipped, while the other sensors show no such pattern. A bias that changes at one moment and stays is a step (its
   residual is the step's direction pattern, with one sign before and the other after), not a drift or a
   temperature effect.
4. Add what the diagnosis names for it and keep going until the verdict reads `adequate`, then check.""",
        "Every sensor's scale factors change with temperature (30 ppm/K), and sensor 4's bias jumps by about "
        "10 nT partway through the recording (perming after a field shock). Each is found only once the "
        "other is in the model or out of the way.",
    ),
}

DEMO_HIDDEN = [("temperature_bias", 1, 2.0)]


def perturbations(hidden):
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
    meta = {
        "description": "magcal demo: Chi et al. (2017) cross, Table 1 errors, 3 nT noise; one effect hidden "
        "(the workbench's Diagnose finds it)"
    }
    mio.write_csv(
        HERE / "demo.csv", ds.replace(metadata={"simulated": "true"}), metadata=meta, float_format=FLOAT_FORMAT
    )


def write_lessons():
    root = HERE / "lessons"
    for seed, (slug, (order, title, hidden, guide, explanation)) in enumerate(LESSONS.items(), start=100):
        folder = root / slug
        folder.mkdir(parents=True, exist_ok=True)
        ds = simulate(hidden, seed)
        mio.write_csv(
            folder / "data.csv",
            ds.replace(metadata={"simulated": "true"}),
            metadata={"lesson": slug},
            float_format=FLOAT_FORMAT,
        )
        (folder / "guide.md").write_text(guide.strip() + "\n", encoding="utf-8")
        doc = {
            "title": title,
            "order": order,
            "data": "data.csv",
            "guide": "guide.md",
            "answer": {"effects": [label(n, s) for n, s, _ in hidden], "explanation": explanation},
            "made_by": "assets/make_assets.py",
            "seed": seed,
        }
        (folder / "lesson.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


#: The real-recording lesson: its folder, the converted recording it is cut from (``benchmarks/real/``, made by
#: ``fetch.py`` and ``convert.py``; local only) and the decimation (every ``REAL_STEP``-th sample).
REAL_SLUG = "real-qmc5883l"
REAL_SOURCE = HERE.parent / "benchmarks" / "real" / "data" / "qmc_filtered.csv"
REAL_STEP = 4

#: The upstream licence of the QMC5883L recording (tomisuarez2/MagnetometerCalibration, LICENSE at commit
#: eb93f820ffc06155579b7d86928795915eef714a), shipped beside the data as the licence asks.
QMC_LICENSE = """MIT License

Copyright (c) 2025 Tom\u00e1s Su\u00e1rez

Permission is hereby granted, free of charge, to any person obtaining a copy
of this software and associated documentation files (the "Software"), to deal
in the Software without restriction, including without limitation the rights
to use, copy, modify, merge, publish, distribute, sublicense, and/or sell
copies of the Software, and to permit persons to whom the Software is
furnished to do so, subject to the following conditions:

The above copyright notice and this permission notice shall be included in all
copies or substantial portions of the Software.

THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND, EXPRESS OR
IMPLIED, INCLUDING BUT NOT LIMITED TO THE WARRANTIES OF MERCHANTABILITY,
FITNESS FOR A PARTICULAR PURPOSE AND NONINFRINGEMENT. IN NO EVENT SHALL THE
AUTHORS OR COPYRIGHT HOLDERS BE LIABLE FOR ANY CLAIM, DAMAGES OR OTHER
LIABILITY, WHETHER IN AN ACTION OF CONTRACT, TORT OR OTHERWISE, ARISING FROM,
OUT OF OR IN CONNECTION WITH THE SOFTWARE OR THE USE OR OTHER DEALINGS IN THE
SOFTWARE.
"""


def write_real_lesson(source=REAL_SOURCE, step=REAL_STEP):
    """The real-recording lesson's ``data.csv`` (every ``step``-th sample of the converted QMC5883L recording,
    its header lines kept, values to 0.1 nT: the data lie on a 33.3 nT grid), ``LICENSE.md``, ``guide.md`` and
    ``lesson.json``. Skipped (returns False) when the converted recording is not on this machine."""
    source = Path(source)
    if not source.is_file():
        print(f"skipped the lesson {REAL_SLUG}: {source} not found (benchmarks/real/fetch.py, convert.py)")
        return False
    lines = source.read_text(encoding="utf-8").splitlines()
    header = [x for x in lines if x.startswith("#")]
    rows = [x for x in lines if x and not x.startswith("#")]
    columns, data = rows[0], rows[1:]
    rate = None
    out = []
    for x in header:
        key = x[1:].partition(":")[0].strip()
        if key == "rate_Hz":
            rate = float(x.partition(":")[2])
            x = f"# rate_Hz: {rate / step:g}"
        elif key == "time":
            x = (
                f"# time: t = original sample index / {rate or 50:g} Hz (the recording has no time stamps); every "
                f"{step}th sample kept for the magcal lesson {REAL_SLUG}"
            )
        x = x.replace("see FINDINGS.md", "see guide.md")
        out.append(x)
    out.insert(2, "# licence_text: LICENSE.md beside this file (MIT licence of the source repository, kept as it asks)")
    body = []
    for row in data[::step]:
        values = [float(v) for v in row.split(",")]
        body.append(",".join([f"{values[0]:.2f}"] + [f"{v:.1f}" for v in values[1:]]))
    folder = HERE / "lessons" / REAL_SLUG
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "data.csv").write_text("\n".join(out + [columns] + body) + "\n", encoding="utf-8")
    (folder / "LICENSE.md").write_text(QMC_LICENSE, encoding="utf-8")
    (folder / "guide.md").write_text(REAL_GUIDE.strip() + "\n", encoding="utf-8")
    doc = {
        "title": REAL_TITLE,
        "order": 6,
        "data": "data.csv",
        "guide": "guide.md",
        "answer": {"effects": REAL_ANSWER, "explanation": REAL_EXPLANATION},
        "made_by": "assets/make_assets.py",
        "source": "github.com/tomisuarez2/MagnetometerCalibration "
        "'calibration data/filtered_raw_data.csv' (MIT, (c) 2025 Tom\u00e1s Su\u00e1rez; see LICENSE.md)",
    }
    (folder / "lesson.json").write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    return True


REAL_TITLE = "A real sensor: QMC5883L on a hand-turned board"
REAL_ANSWER = ["bias_drift"]
REAL_EXPLANATION = (
    "No answer was hidden here: this is what magcal's loop finds in a real QMC5883L, judged on held-out data. "
    "No instrument term holds. The cubic nonlinearity once seemed to (5 % on held-out data) while its basis was a "
    "power of the noisy readings: such a power follows the readings' own noise along the field, and its fit "
    "compressed the noise (and the shrinking of a filtered stream at high turn rates), on held-out samples too. "
    "Taken from the denoised readings, it gains nothing (score LM 10 on 3 parameters); the quadratic term gains "
    "under 1 % on held-out blocks. bias_drift takes the held-out blocks from about 1052 to 1029 nT: a slow wander "
    "of the offsets during this record (the x axis wanders in the still minute too), a record-only term that says "
    "nothing about the next recording (the later stretch does not improve). What remains, about 1.27x the floor "
    "of 762 nT (the still stretches' field magnitude shows no slower noise), is a small degree-3 direction pattern "
    "and a correlation in time that grows with the turn rate, which no catalogue term that holds on held-out data "
    "removes."
)
REAL_GUIDE = """
Every other lesson is simulated: the answer was put in by the simulator. This one is a **real recording**: a
QMC5883L three-axis magnetometer (GY-63 board, Arduino UNO) turned by hand for about 7 minutes after a still
minute, from Tom\u00e1s Su\u00e1rez's MagnetometerCalibration project
(github.com/tomisuarez2/MagnetometerCalibration, `calibration data/filtered_raw_data.csv`, MIT licence: see
`LICENSE.md` beside the data). It was logged at 50 Hz; this copy keeps every 4th sample (12.5 Hz, 5 687 samples)
to stay small. Nobody hid anything: there is no "right" answer, only what holds on data the fit did not see.

## 1. What real data look like

Open the file (or `magcal calibrate data.csv`) and read the **Data quality** part of the report before the fit.

* **Quantization.** The part counts in steps of 33.3 nT (3000 LSB/G) and its readings here move on a grid of 5
  counts, 167 nT. Its floor, q/sqrt(12) = 48 nT, is far below the noise: it does not matter here.
* **Noise far above a simulator's.** The second differences in the still stretches give about 760 nT per axis
  (the simulated lessons have 3 nT). The still stretches' own scatter is larger (1.3-2 uT): the x axis wanders
  slowly while the board lies still. Which one is the noise? The fast scatter; the wander is a slow error.
* **A hard iron six times the field.** The fitted bias is about (206.5, 8.4, 116) uT, 237 uT in all, against a
  fitted field of 35.7 uT: the board's own magnetism dominates the readings. The axes' gains differ by 2.2x
  (gauge-free scales 1.01, 0.67, 1.48) and the axes are 84.5-89 deg apart. A good ellipsoid fit takes all of that
  out: this is what a calibration is for.
* **The unit is a decision.** The sketch asks for the +-2 G range (12000 LSB/G), which would put the field at
  8.9 uT, weaker than anywhere on Earth; 3000 LSB/G gives 35.7 uT. There is no reference field, so the field is
  fitted, and every RMS below is relative to this choice of LSB.

## 2. The base fit

Calibrate with the base model (bias, scale, non-orthogonality). The total-field RMS falls from 212 uT to about
986 nT, 1.29x the floor of 762 nT. The noise's text says where the floor comes from: the second differences in the
still stretches; their field magnitude, over the time the board takes to turn through a radian, shows no slower
noise to add (the x axis's wander is across the field there). The report's held-out validation fits alternating
blocks of time and scores the blocks between: about 1052 nT there.

## 3. Diagnose, and judge on held-out data

Run **Diagnose**. The verdict is `unexplained`, with candidates ranked and a **held-out** column: a term is
recommended only if the error falls on samples its fit did not see.

1. Which candidate lowers the held-out error, on the blocks *and* on the later stretch? Which ones lower only the
   in-sample error? (Compare the drift, the reference drift and the quadratic nonlinearity.)
2. Where is the cubic nonlinearity? Its basis is a power of the *denoised* reading (the reading the fitted model
   predicts from the sample's direction), and it gains nothing here. A power of the noisy reading would seem to
   gain 5 % on held-out data: it follows the reading's own noise along the field, so its fit compresses the noise
   wherever an axis is large, with no nonlinearity at all. An AMR part in a board field six times the Earth's is
   where a nonlinearity would be plausible; these data do not show one.
3. The drift holds on the held-out blocks. Is it an instrument term or a record-only one? What does
   "record-only" mean when you apply this calibration to tomorrow's data (look at the later stretch)?

## 4. What remains

After the drift the RMS is about 967 nT, 1.27x the floor, and the verdict still reads `unexplained`.
"Unexplained" does not mean "wrong": it means the residual still has structure (here a small degree-3 pattern over
the field direction and a correlation in time) and no catalogue term that holds on held-out data removes it. Look at the terms ranked below the line: some lower the in-sample RMS and raise the held-out one.
Adding them would fit this recording's noise, not the sensor.

Two more things to look at: the residual against time in the still minute at the start (the noise and the
wander), and the error against the turn rate (it grows from about 865 to 1115 nT from the slowest to the fastest
quarter of the full recording: a filter shrinks a turning vector; neither an axis timing skew nor a lag of the
output explains it).

**Check my model** when you have the terms that hold.
"""


#: The vehicle lesson: where and when it was flown (the reference the student types), and its record.
VEHICLE_SLUG = "cannot-tumble"
VEHICLE_SITE = {"lat_deg": 53.0, "lon_deg": 4.5, "alt_m": 1500.0, "date": "2024-06-01"}
VEHICLE_SEED = 2929
VEHICLE_SAMPLES = 2000
VEHICLE_ATTITUDE_NOISE_DEG = 0.05
VEHICLE_TITLE = "A vehicle that cannot tumble"
VEHICLE_GUIDE = """
A survey aircraft carries a fluxgate in its tail. It cannot be turned through every direction on a bench: the
record is a calibration flight of three full turns, banking to +-20 deg and pitching +-10 deg, with the aircraft's
attitude from its INS in `roll_deg, pitch_deg, yaw_deg` (body x forward, y right, z down; world north-east-down).
The flight was over the sea at **53.0 N, 4.5 E, 1500 m** above the ellipsoid, on **2024-06-01**. Nobody measured
the field there: the file has no reference column.

1. **Run the chosen method** (Calibrate tab): the total-field fit. Read the message and the *Vector model* table
   under the step buttons. Is the fit determined by these data? In the View tab, where on the sphere do the corrected
   samples lie, and where not?
2. Open *Reference from a location (IGRF)* (Calibrate tab) and type where and when the aircraft flew; press *Use
   this location (IGRF)*. What reference field does it set, and what does that change in the total-field fit?
3. **Run the vector fit (attitude-aided)**. Compare the two columns of the table: the total-field RMS, the world
   components N, E, D, the mounting, the attitude noise. Which figures can the total-field fit not give at all, and
   why? Is the world residual at the sensor's noise, or at something else (what does 0.05 deg of attitude error do
   to a 49 uT field)?
4. View tab: tick **Show the vehicle view** and press *Play* in the Time window. The green arrow is the model field, the blue
   one the measured field rotated to the world, the red one their difference, exaggerated. Does the red arrow
   follow the turns, or only jitter?
5. **Check my model** once the vector fit has run.
"""
VEHICLE_EXPLANATION = (
    "The fluxgate is mounted ROLL_180_YAW_90 (ArduPilot's rotation 10: sensor x along the body's y, y along x, z up "
    "instead of down), turned 2 deg off that right angle about a tilted axis; its bias is about 1.5 uT per axis and "
    "its scale and soft iron a few per cent. A flight that turns in yaw and tilts 20 deg sees a cone of field "
    "directions: the total-field fit extrapolates to the rest of the sphere (magcal warns of the coverage) and can "
    "never say how the sensor sits in the aircraft. With the attitude and the IGRF field vector every sample gives "
    "three equations: the vector fit finds the right angle, the 2 deg, and a world residual of about 0.05 deg x |B| "
    "(~35-40 nT per horizontal component), the attitude error's floor, with |B| at the 3 nT sensor noise."
)


def write_vehicle_lesson():
    """The vehicle lesson (``cannot-tumble``): data, guide, answer. The field is IGRF at :data:`VEHICLE_SITE`."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from magcal.checks.reference import igrf_ned_nT
    from magcal.data.attitude import wxyz_rotation
    from magcal.data.vehicle import simulate_vehicle
    from magcal.geometry.orientations import describe_right_angle, nearest_right_angle

    site = VEHICLE_SITE
    ned = igrf_ned_nT(site["lat_deg"], site["lon_deg"], site["alt_m"] / 1000.0, site["date"])[0]
    ds, truth = simulate_vehicle(
        n=VEHICLE_SAMPLES,
        rate_hz=10.0,
        turns=3.0,
        roll_max_deg=20.0,
        pitch_max_deg=10.0,
        noise_nT=3.0,
        attitude_noise_deg=VEHICLE_ATTITUDE_NOISE_DEG,
        seed=VEHICLE_SEED,
        field_ned_nT=tuple(float(v) for v in ned),
        off_deg=2.0,
    )
    yaw, pitch, roll = wxyz_rotation(ds.attitude_wxyz).as_euler("ZYX", degrees=True).T
    extra = {"roll_deg": roll, "pitch_deg": pitch, "yaw_deg": np.mod(yaw, 360.0)}
    data = ds.replace(attitude_wxyz=None, extra=extra, metadata={"simulated": "true"})
    folder = HERE / "lessons" / VEHICLE_SLUG
    folder.mkdir(parents=True, exist_ok=True)
    mio.write_csv(
        folder / "data.csv",
        data,
        metadata={
            "lesson": VEHICLE_SLUG,
            "vehicle": "aeroplane",
            "attitude": "roll_deg, pitch_deg, yaw_deg: aerospace ZYX, body (x forward, y right, z down) -> NED",
            "site": f"{site['lat_deg']} N, {site['lon_deg']} E, {site['alt_m']:g} m, {site['date']}",
        },
        float_format=FLOAT_FORMAT,
    )
    mounting = truth.sensors[0].mounting
    right, off = nearest_right_angle(mounting)
    (folder / "guide.md").write_text(VEHICLE_GUIDE.strip() + "\n", encoding="utf-8")
    doc = {
        "title": VEHICLE_TITLE,
        "order": 7,
        "data": "data.csv",
        "guide": "guide.md",
        "answer": {
            "effects": [],
            "mounting": [describe_right_angle(right).split(" ")[0]],
            "mounting_off_deg": round(float(off), 3),
            "mounting_tolerance_deg": 0.1,
            "explanation": VEHICLE_EXPLANATION,
        },
        "made_by": "assets/make_assets.py",
        "seed": VEHICLE_SEED,
        "site": site,
        "truth": {
            "bias_nT": np.round(truth.sensors[0].bias_nT, 1).tolist(),
            "mounting_rotvec_deg": np.round(Rotation.from_matrix(mounting).as_rotvec(degrees=True), 3).tolist(),
            "attitude_noise_deg": VEHICLE_ATTITUDE_NOISE_DEG,
            "noise_nT": 3.0,
        },
    }
    (folder / "lesson.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


#: The drone lesson (issue 40): a compass that sees the battery current, on the vector model.
DRONE_SLUG = "drone-current"
DRONE_SEED = 4040
DRONE_SAMPLES = 2400
DRONE_CURRENT_nT_PER_A = 25.0
DRONE_ATTITUDE_NOISE_DEG = 0.02
DRONE_TITLE = "A drone's compass sees its battery current"
DRONE_GUIDE = """
A quadcopter flew a calibration pattern for four minutes: four slow turns, banking to +-20 deg and pitching
+-10 deg. Its log holds the compass (`x, y, z`, nT), the autopilot's attitude (`qw..qz`, body -> NED), the field
vector where it flew (`ref_n, ref_e, ref_d`, from IGRF), the battery's current (`current_A`) and the board's
temperature (`temp`). With an attitude and a field vector, **Diagnose** and **Add** work on the vector model: the
compass's bias, matrix and mounting fitted so that its reading, turned to the world by the attitude, matches the
field's north, east and down components.

1. **Model** tab: press **Diagnose**. It fits the vector model first, then refits it with every effect of the
   catalogue the record can show and judges each on the last part of the flight, as `magcal apply` would use it.
   Read the verdict, the world RMS against its noise floor, and the table: which effect is recommended, and does
   its gain hold on the later part?
2. Choose candidates in the *Candidate* list and look at the evidence plots under the history: the world
   residuals north, east, down and |B| against the channel each candidate follows. Which channel do they line up
   with? Is the temperature, which rises through the flight, to blame?
3. **Add the candidate and refit**. How far do the world components fall in the history plot, and how close do
   they come to the floor? What is left: only the attitude's error, or more?
4. **View** tab: tick **Show the vehicle view** and play the time window. The red arrow is the world residual
   (its exaggeration is set by the model before Add): does it still follow the battery current (`current_A`)?
5. **Check my model** (Lessons tab).
"""
DRONE_EXPLANATION = (
    "The compass sits near the battery leads: every ampere adds a field of about (25, -17.5, 12.5) nT along the "
    "compass's axes (current_field, k per ampere of current_A; ArduPilot's COMPASS_MOT_X/Y/Z and PX4's "
    "CAL_MAGn_[XYZ]COMP hold exactly this). At 3-25 A that is 100-800 nT, which the base vector model spreads "
    "over its bias and matrix and leaves as world residuals of 80-140 nT per component that follow the current. "
    "The temperature rises through the flight and with the current (the electronics warm), but its candidates "
    "explain little of it. With current_field the world components fall to the attitude error's floor (0.02 deg "
    "of a 48.8 uT field: about 16-17 nT north and east, 8 nT down) and |B| to the 3 nT sensor noise; the term "
    "carries to the next flight (magcal export writes it as the firmware's motor compensation)."
)


def write_drone_lesson():
    """The drone lesson (``drone-current``): data, guide, answer (``"model": "vector"``)."""
    import numpy as np

    from magcal.data.vehicle import simulate_vehicle, vehicle_truth

    effect = EFFECTS["current_field"]()
    truth = vehicle_truth(seed=DRONE_SEED, off_deg=1.0)
    ds, _ = simulate_vehicle(
        truth,
        n=DRONE_SAMPLES,
        rate_hz=10.0,
        turns=4.0,
        roll_max_deg=20.0,
        pitch_max_deg=10.0,
        noise_nT=3.0,
        attitude_noise_deg=DRONE_ATTITUDE_NOISE_DEG,
        seed=DRONE_SEED,
        perturbations=[effect.perturbation(DRONE_CURRENT_nT_PER_A, None)],
        log_current=True,
        temperature=True,
    )
    folder = HERE / "lessons" / DRONE_SLUG
    folder.mkdir(parents=True, exist_ok=True)
    mio.write_csv(
        folder / "data.csv",
        ds.replace(metadata={"simulated": "true"}),
        metadata={
            "lesson": DRONE_SLUG,
            "vehicle": "quadcopter",
            "attitude": "qw, qx, qy, qz: body (x forward, y right, z down) -> NED",
            "reference": "ref_n, ref_e, ref_d: the field vector (IGRF) where it flew, nT",
        },
        float_format=FLOAT_FORMAT,
    )
    (folder / "guide.md").write_text(DRONE_GUIDE.strip() + "\n", encoding="utf-8")
    doc = {
        "title": DRONE_TITLE,
        "order": 8,
        "data": "data.csv",
        "guide": "guide.md",
        "answer": {"effects": ["current_field"], "model": "vector", "explanation": DRONE_EXPLANATION},
        "made_by": "assets/make_assets.py",
        "seed": DRONE_SEED,
        "truth": {
            "current_field_nT_per_A": np.round(effect.true_params(DRONE_CURRENT_nT_PER_A, 0), 3).tolist(),
            "bias_nT": np.round(truth.sensors[0].bias_nT, 1).tolist(),
            "attitude_noise_deg": DRONE_ATTITUDE_NOISE_DEG,
            "noise_nT": 3.0,
        },
    }
    (folder / "lesson.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


#: The compass lesson (issue 42): a board whose magnetometer sits 2 deg off its accelerometer.
COMPASS_SLUG = "tilted-compass"
COMPASS_SEED = 4242
COMPASS_TITLE = "The compass that points wrong when tilted"
COMPASS_GUIDE = """
A hiking compass (or a phone, or a cave-survey instrument) carries a MEMS magnetometer beside an accelerometer on
one board. The accelerometer says which way is down; the compass's heading is the horizontal part of the field in
the frame the accelerometer defines. Its owner tumbled it by hand, holding it still for a second or two at each of
24 attitudes: `x, y, z` are the magnetometer (nT), `ax, ay, az` the accelerometer (g, up when still), `gx_dps..` the
gyro. Level, the compass reads right; tilted, it points wrong.

1. **Run the gravity fit (beside the accelerometer)**: the first screen's *Step 1* button (or the Calibrate tab,
   *Gravity model*). Read the table: the mounting it finds, the dip's spread of both fits, the heading difference
   between them. Why is the dip (the angle between the field and gravity) the figure that sees what |B| cannot?
2. **Run the chosen method** (Calibrate tab): the total-field fit. Is |B| at the noise? Can a total-field fit say
   how the magnetometer's axes sit against the accelerometer's?
3. Look at the two plots: the dip over time and against the tilt, and the compass rose. Where is the total-field
   fit's heading wrong, and by how much? At this inclination, how much heading does a degree of tilt error cost?
4. View tab: tick **Show the accelerometer's cloud and sphere**. Which samples measure gravity?
5. **Check my model** once the gravity fit has run.
"""
COMPASS_EXPLANATION = (
    "The magnetometer is mounted ROLL_180_YAW_90 against the accelerometer (its x along the board's y, y along x, z "
    "up: a part whose axes the datasheet turns) and a further 2 deg off that right angle about a tilted axis, with a "
    "board's hard iron (15 uT per axis) and soft iron (5 %); the accelerometer has a 0.03 g bias and 2 % gains. "
    "A total-field fit calibrates |B| but cannot see a rotation, so with the right angle taken from the datasheet "
    "its heading is off by the 2 deg times up to tan(I) + 1 at an inclination I of 64 deg: 2-3 deg, most when "
    "tilted. The dip is the same at every attitude only if the magnetometer's axes are the accelerometer's: the "
    "gravity fit finds the right angle and the 2 deg, and its heading sits at the sensors' noise (about 0.5 deg per "
    "still sample)."
)


def write_gravity_lesson():
    """The compass lesson (``tilted-compass``): data, guide, answer."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from magcal.data.board import SWAPPED_MOUNTING, simulate_board
    from magcal.geometry.orientations import describe_right_angle, nearest_right_angle

    ds, truth, _ = simulate_board(
        n_poses=24, rate_hz=25.0, mounting=SWAPPED_MOUNTING, seed=COMPASS_SEED, inclination_deg=64.0
    )
    g = 9.80665
    extra = dict(ds.extra)
    for k in ("ax", "ay", "az"):
        extra[k] = np.asarray(extra[k]) / g
    data = ds.replace(extra=extra, metadata={"simulated": "true", "accel_units": "g"})
    folder = HERE / "lessons" / COMPASS_SLUG
    folder.mkdir(parents=True, exist_ok=True)
    mio.write_csv(
        folder / "data.csv",
        data,
        metadata={"lesson": COMPASS_SLUG, "accelerometer": "ax, ay, az in g (specific force: up when still)"},
        float_format=FLOAT_FORMAT,
    )
    right, off = nearest_right_angle(truth.mounting)
    (folder / "guide.md").write_text(COMPASS_GUIDE.strip() + "\n", encoding="utf-8")
    doc = {
        "title": COMPASS_TITLE,
        "order": 8,
        "data": "data.csv",
        "guide": "guide.md",
        "fit": "gravity",
        "answer": {
            "effects": [],
            "mounting": [describe_right_angle(right).split(" ")[0]],
            "mounting_off_deg": round(float(off), 3),
            "mounting_tolerance_deg": 0.2,
            "explanation": COMPASS_EXPLANATION,
        },
        "made_by": "assets/make_assets.py",
        "seed": COMPASS_SEED,
        "truth": {
            "mag_bias_nT": np.round(truth.mag_bias_nT, 1).tolist(),
            "mounting_rotvec_deg": np.round(Rotation.from_matrix(truth.mounting).as_rotvec(degrees=True), 3).tolist(),
            "accel_bias_m_s2": np.round(truth.accel_bias_m_s2, 4).tolist(),
            "inclination_deg": round(truth.inclination_deg, 3),
        },
    }
    (folder / "lesson.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


#: The compensation lesson: a survey drone whose battery current Tolles-Lawson does not model.
SURVEY_SLUG = "survey-drone-current"
SURVEY_SEED = 5353
SURVEY_CURRENT_nT_PER_A = (1.5, -1.0, 0.8)
SURVEY_FOM_RATIO = 1.2
SURVEY_FORMAT = "%.10g"  # 1e-5 nT at 50 000 nT: far below the scalar's 0.02 nT noise
SURVEY_TITLE = "A survey drone whose battery current the Tolles-Lawson fit misses"
SURVEY_GUIDE = """
A drone carrying a survey magnetometer flew its compensation box before a survey line: four headings, and on each
three rolls of +-10 deg, three pitches of +-5 deg and three yaws of +-5 deg. Its log holds the scalar magnetometer
(`scalar_nT`, on a boom), the fluxgate beside it (`x, y, z`, nT, the direction of the field), the attitude
(`roll_deg, pitch_deg, yaw_deg`), what the battery delivers, in amperes (the column ending in `_A`), and the
platform's temperature (`temp`: it warms through the flight). The platform's own field spoils the survey:
Tolles-Lawson models its permanent, induced and eddy parts from the fluxgate's direction cosines, and the figure of
merit (FOM: the sum of the 12 band-passed peak-to-peak values in the maneuvers) judges it.

1. Press the first screen's **Step 1** button: the Tolles-Lawson fit. Read the status: the FOM before and after,
   the improvement ratio. Calibrate tab, *Compensation*: the band-passed scalar before and after against time,
   the maneuvers shaded, and the FOM table per heading and maneuver. Is what is left only at the maneuvers?
2. **Step 2**: Diagnose. Each term beyond Tolles-Lawson is refitted with one maneuver in four held out and judged
   by the FOM on the maneuvers its fit did not see. Which one brings the FOM down to the scalar's noise?
3. **Step 3**: add the advice and refit. How far does the FOM fall, and how close to what the noise leaves?
4. **Check my model** (Lessons tab).
"""
SURVEY_EXPLANATION = (
    "The battery leads run past the boom: every ampere of the drone's current adds a field of (1.5, -1.0, 0.8) nT "
    "in the body frame. The current follows the throttle, which changes in the maneuvers, so the field is in the "
    "band the FOM measures, but it follows neither the attitude nor the rates that Tolles-Lawson's terms are made "
    "of: the TL fit leaves it (and bends its coefficients to soak up what it can). The term current (a field per "
    "ampere of current_A, three coefficients) follows it, and the FOM falls to what the scalar's 0.02 nT noise "
    "leaves, as the true compensation does."
)


def write_compensation_lesson():
    """The compensation lesson (``survey-drone-current``): data, guide, answer (``"model": "compensation"`` and the
    true compensation's FOM)."""
    import numpy as np
    import pandas as pd

    from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
    from magcal.diagnosis.fom import figure_of_merit
    from magcal.modes import COMPENSATION

    platform = CompensationPlatform(current_nT_per_A=np.array(SURVEY_CURRENT_nT_PER_A))
    flight = simulate_compensation_flight(SURVEY_SEED, platform=platform)
    frame = pd.DataFrame(
        {
            "t": flight.time_s,
            "x": flight.flux_nT[:, 0],
            "y": flight.flux_nT[:, 1],
            "z": flight.flux_nT[:, 2],
            "scalar_nT": flight.scalar_nT,
            "roll_deg": flight.attitude_deg[:, 0],
            "pitch_deg": flight.attitude_deg[:, 1],
            "yaw_deg": flight.attitude_deg[:, 2],
            "current_A": flight.current_A,
            "temp": flight.temperature_C,
        }
    )
    folder = HERE / "lessons" / SURVEY_SLUG
    folder.mkdir(parents=True, exist_ok=True)
    frame.to_csv(folder / "data.csv", index=False, float_format=SURVEY_FORMAT)
    ds = mio.read_csv(folder / "data.csv")
    maneuvers = COMPENSATION.fit(ds).fom.after.maneuvers  # the maneuvers the page's FOM sums over
    true_fom = figure_of_merit(flight.truth.compensated_nT(flight.scalar_nT), maneuvers, flight.sample_rate_hz)
    (folder / "guide.md").write_text(SURVEY_GUIDE.strip() + "\n", encoding="utf-8")
    doc = {
        "title": SURVEY_TITLE,
        "order": 9,
        "data": "data.csv",
        "guide": "guide.md",
        "answer": {
            "effects": ["current"],
            "model": "compensation",
            "true_fom_nT": round(float(true_fom.fom_nT), 4),
            "fom_ratio": SURVEY_FOM_RATIO,
            "explanation": SURVEY_EXPLANATION,
        },
        "made_by": "assets/make_assets.py",
        "seed": SURVEY_SEED,
        "truth": {
            "current_nT_per_A": list(SURVEY_CURRENT_nT_PER_A),
            "tl18": np.round(flight.truth.tl18(flight.sample_rate_hz), 4).tolist(),
            "scalar_noise_nT": 0.02,
        },
    }
    (folder / "lesson.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def main():
    write_demo()
    write_lessons()
    write_real_lesson()
    write_vehicle_lesson()
    write_drone_lesson()
    write_gravity_lesson()
    write_compensation_lesson()
    print(f"wrote {HERE / 'demo.csv'} and {len(LESSONS)} lessons under {HERE / 'lessons'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
