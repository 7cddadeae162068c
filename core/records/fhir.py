"""A session's results as a FHIR R4 ``Bundle`` (SPEC §7): one ``Observation`` per complete trial, a
``component`` per measured angle and mismatch (valueQuantity in degrees, UCUM ``deg``), the body site
(ankle joint, SNOMED CT) with its laterality, and the effective time (when the trial was scanned).

Built as plain JSON (no dependency at run time); the tests validate it with fhir.resources. The scanned
leg is the right one in the SPEC's frame (marks 3 and 4 on its right-hand, lateral side), so the
laterality is right unless the patient's record names one affected side.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from anklescan.core.atomic import write_text_atomic
from anklescan.core.errors import AnkleScanError
from anklescan.core.records.tables import TrialExport
from anklescan.core.vocabulary import TrialState

SNOMED = "http://snomed.info/sct"
UCUM = "http://unitsofmeasure.org"
LOCAL = "urn:anklescan:angle"
ANKLE_JOINT = ("70258002", "Ankle joint structure")
LATERALITY = {"right": ("24028007", "Right"), "left": ("7771000", "Left")}
LATERALITY_URL = "http://hl7.org/fhir/StructureDefinition/bodySite-laterality"
COMPONENTS = {
    "leg_inversion": "Leg inversion angle",
    "leg_plantar_flexion": "Leg plantar-flexion angle",
    "table_inversion": "Adjusted table inversion angle",
    "table_plantar_flexion": "Adjusted table plantar-flexion angle",
    "mismatch_inversion": "Mismatch of inversion (adjusted - reference table)",
    "mismatch_plantar_flexion": "Mismatch of plantar flexion (adjusted - reference table)",
    "reference_inversion": "Reference table inversion angle",
    "reference_plantar_flexion": "Reference table plantar-flexion angle",
}


def _deg(value: float, sd: float | None = None) -> dict[str, Any]:
    q = {"value": round(float(value), 4), "unit": "deg", "system": UCUM, "code": "deg"}
    return q if sd is None else q


def _effective(created: str) -> str:
    """ISO 8601 with a time zone, as FHIR's dateTime needs one when a time is given."""
    t = _dt.datetime.fromisoformat(created)
    if t.tzinfo is None:
        t = t.astimezone()
    return t.isoformat(timespec="seconds")


def _side(affected_side: str | None) -> str:
    return affected_side if affected_side in LATERALITY else "right"


def observation(trial: TrialExport, patient_ref: str, side: str) -> dict[str, Any]:
    """One complete trial (an export row of core.records.tables) as an Observation."""
    comps = []
    for key, text in COMPONENTS.items():
        ref = key.startswith("reference_")
        v = trial.value(key)
        if v is None or not math.isfinite(v):
            continue
        comp: dict[str, Any] = {"code": {"coding": [{"system": LOCAL, "code": key, "display": text}], "text": text},
                      "valueQuantity": _deg(v)}
        sd = None if ref else trial.sd(key)
        if sd is not None and math.isfinite(sd):
            comp["referenceRange"] = [{"low": _deg(v - 2 * sd), "high": _deg(v + 2 * sd),
                                       "text": f"measured value ± 2 SD (SD {sd:.3f} deg)"}]
        comps.append(comp)
    code, display = LATERALITY[side]
    obs = {"resourceType": "Observation", "id": f"trial-{trial.trial}", "status": "final",
           "category": [{"coding": [{"system": "http://terminology.hl7.org/CodeSystem/observation-category",
                                     "code": "exam", "display": "Exam"}]}],
           "code": {"coding": [{"system": LOCAL, "code": "ankle-position-sense-trial",
                                "display": "Ankle joint position sense trial (structured-light scan)"}],
                    "text": f"Ankle joint position sense trial, {trial.condition}"},
           "subject": {"reference": patient_ref},
           "effectiveDateTime": _effective(trial.created),
           "bodySite": {"coding": [{"system": SNOMED, "code": ANKLE_JOINT[0], "display": ANKLE_JOINT[1]}],
                        "extension": [{"url": LATERALITY_URL, "valueCodeableConcept": {
                            "coding": [{"system": SNOMED, "code": code, "display": display}]}}],
                        "text": f"{display.lower()} ankle joint"},
           "method": {"text": "structured-light 3-D scan of seven marks (AnkleScan)"},
           "note": [{"text": f"session {trial.session}, trial {trial.trial}, condition {trial.condition}, "
                             f"calibration {trial.calibration}"
                             + (f"; excluded from the statistics: {trial.excluded_reason}"
                                if trial.excluded == "true" else "")}],
           "component": comps}
    return obs


def session_bundle(trials: Sequence[TrialExport], patient_code: str, affected_side: str | None) -> dict[str, Any]:
    """A ``collection`` Bundle: the Patient (its pseudonymous code only) and one Observation per
    complete trial of ``trials`` (one session's export rows) with any measured value."""
    done = [t for t in trials if t.status == TrialState.COMPLETE and any(
        t.value(k) is not None for k in COMPONENTS if not k.startswith("reference_"))]
    if not done:
        # say which trials were looked at and their states: `--trial N` asks for one, not the session
        states = ", ".join(f"trial {t.trial} {t.status}" for t in trials[:10]) + (", …" if len(trials) > 10 else "")
        raise AnkleScanError(f"no complete trial with a measured angle to export ({states or 'no trials'}); "
                             "FHIR holds complete trials only; nothing written")
    pid = "patient-1"
    patient = {"resourceType": "Patient", "id": pid,
               "identifier": [{"system": "urn:anklescan:patient-code", "value": patient_code}]}
    side = _side(affected_side)
    patient_ref = f"urn:uuid:{uuid.uuid5(uuid.NAMESPACE_URL, 'anklescan:patient:' + patient_code)}"
    entries: list[dict[str, Any]] = [{"fullUrl": patient_ref, "resource": patient}]
    for t in done:
        entries.append({"fullUrl": f"urn:uuid:{uuid.uuid4()}", "resource": observation(t, patient_ref, side)})
    return {"resourceType": "Bundle", "type": "collection",
            "timestamp": _dt.datetime.now().astimezone().isoformat(timespec="seconds"), "entry": entries}


def write_bundle(bundle: dict[str, Any], path: Path) -> None:
    write_text_atomic(path, json.dumps(bundle, indent=2, ensure_ascii=False) + "\n")
