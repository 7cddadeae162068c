"""A simulated patient: who stands on the tables and how they set the adjustable one.

The paper's protocol: the left foot stands on the reference table, set by the clinician to the
reference angles; the patient sets the right (adjustable, scanned) table to what feels the same.
The error of that setting is this model: a bias, a gain on each reference angle and noise, all
in degrees, smaller in shoes (the paper's finding). ``anklescan demo`` and the app's simulated
rig share it, so the app's simulated trials look like the demo's.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from anklescan.core.vocabulary import CONDITIONS, MarkKind

if TYPE_CHECKING:  # numpy is imported where a patient is made: the app's settings read PatientProfile at start-up
    import numpy as np

    from anklescan.hardware.sim_scene import Scene


@dataclass(frozen=True)
class SimPatient:
    code: str
    sprain_count: int
    last_sprain: str | None
    notes: str
    # the table setting error, degrees: bias + gain_inv * inversion + gain_pf * plantar flexion + noise
    bias: tuple[float, float]  # (inversion, plantar flexion)
    gain_inv: tuple[float, float]
    gain_pf: tuple[float, float]
    noise: float
    shoes_factor: float  # shoes give the ankle a better sense of the angle (the paper's finding)
    # the clinic's marks for this patient: type, diameter (mm), and whether the session is told
    # the size (else measured from each capture)
    marks: tuple[MarkKind, float, bool] = (MarkKind.PLATE, 15.0, False)


PATIENTS = (
    SimPatient("SIM-01", 3, "2026-08-14", "simulated: recurrent sprains, right ankle", (1.5, -1.0), (0.12, 0.0),
               (0.05, -0.08), 1.6, 0.55, (MarkKind.STICKER, 12.0, False)),
    SimPatient("SIM-02", 0, None, "simulated: no sprain history", (0.2, 0.1), (0.02, 0.0), (0.0, -0.01), 0.7, 0.8,
               (MarkKind.PLATE, 15.0, True)),
)


def table_setting(p: SimPatient, condition: str, inversion: float, pf: float,
                  rng: np.random.Generator) -> tuple[float, float]:
    """The adjustable table's (inversion, plantar flexion) as ``p`` sets it to match the reference."""
    f = p.shoes_factor if condition == "shoes" else 1.0
    err = [f * (p.bias[i] + p.gain_inv[i] * inversion + p.gain_pf[i] * pf + rng.normal(0.0, p.noise)) for i in (0, 1)]
    return inversion + err[0], pf + err[1]


class PatientProfile(Enum):
    """Who stands on the app's simulated rig (chosen in Camera setup)."""

    NO_SPRAIN = "no sprain"
    SPRAIN_HISTORY = "sprain history"

    @property
    def patient(self) -> SimPatient:
        return PATIENTS[1] if self is PatientProfile.NO_SPRAIN else PATIENTS[0]

    @property
    def label(self) -> str:
        return {PatientProfile.NO_SPRAIN: "No sprain", PatientProfile.SPRAIN_HISTORY: "Sprain history"}[self]

    @classmethod
    def parse(cls, value: str) -> PatientProfile:
        """The profile named ``value``; the default (no sprain) for an unknown or stale setting."""
        try:
            return cls(str(value).strip().lower())
        except ValueError:
            return cls.NO_SPRAIN


@dataclass(frozen=True)
class Stance:
    """One trial's set-up: the reference table as the clinician set it, the adjustable table as
    the simulated patient set it (degrees), and the marks the patient wears."""

    reference: tuple[float, float]
    table: tuple[float, float]
    condition: str
    mark_type: MarkKind
    mark_diameter_mm: float

    @property
    def mismatch(self) -> tuple[float, float]:
        """The true table mismatch (adjustable minus reference): what a trial should measure."""
        return self.table[0] - self.reference[0], self.table[1] - self.reference[1]


class SimulatedPatient:
    """A patient of ``profile`` answering the clinician's references, trial after trial (a seeded
    generator: the same seed gives the same settings)."""

    def __init__(self, profile: PatientProfile = PatientProfile.NO_SPRAIN, seed: int | None = None) -> None:
        import numpy as np

        self.profile = profile
        self._rng = np.random.default_rng(seed)

    @property
    def patient(self) -> SimPatient:
        return self.profile.patient

    def stance(self, reference: tuple[float | None, float | None], condition: str) -> Stance:
        """How the patient stands for a trial at ``reference`` (None: a reference not typed, 0)."""
        if condition not in CONDITIONS:
            raise ValueError(f"condition must be one of {', '.join(CONDITIONS)}, not {condition!r}")
        inv, pf = (float(v) if v is not None else 0.0 for v in reference)
        table = table_setting(self.patient, condition, inv, pf, self._rng)
        mark_type, diameter, _ = self.patient.marks
        return Stance((inv, pf), (float(table[0]), float(table[1])), condition, mark_type, float(diameter))

    def scene(self, stance: Stance) -> Scene:
        """The simulated scene of ``stance``: the right leg on the adjustable table, its marks on."""
        from anklescan.hardware.sim_scene import leg_scene

        return leg_scene(*stance.table, mark_type=stance.mark_type, mark_radius=stance.mark_diameter_mm / 2)
