"""A calibration sweep's adjustment in the service (issue 12, ``POST /api/v1/calibrations``).

A calibration sweep is a measurement job with target ``"calibration"``: the rig sweeps as for
any measurement (the raw MCAP log, progress, cancellation, a fault stopping the motor and failing
the job with its reason), the sweep is mapped with the rig's ``[kinematics]`` as configured (never
with the active calibration: the adjustment starts from the nominal rig), and instead of a
cylinder or an elbow the rig model is adjusted to the sweep's raw ``(l, alpha, beta, omega)`` by
:func:`lrms.calibration.calibrate`, as ``lrms calibrate LOG.mcap`` does on the same raw log.

:func:`calibration_result` runs in the rig process (its fit worker); :func:`store_calibration`
runs in the service process, where the calibration store is: the calibration is stored (and
activated when the request says so) in the transaction that marks the job done, and the job's
result holds its id and summary. A cancel that arrives during the adjustment ends the job
cancelled with nothing stored.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.calstore import CalibrationStore
    from service.config import RigConfig
    from service.jobs import JobContext
    from service.models import JobRequest
    from service.sweep import MappedSweep

#: The job result's key of the whole calibration, from the rig process to the service process
#: (which stores it and replaces it by ``calibration_id``).
RESULT_KEY = "calibration_result"


def calibration_result(mapped: MappedSweep, request: JobRequest, config: RigConfig) -> dict[str, Any]:
    """Adjust the rig model to the sweep (:func:`lrms.calibration.calibrate`, one rig pose): the
    calibration's JSON under :data:`RESULT_KEY` and the number of beams it used. Raises the
    calibration's own errors (too few beams, no planes or spheres found: ``CalibrationError``)."""
    from lrms.calibration import AdjustOptions, Artefact, CalibrationOptions, Observations, calibrate
    from lrms.cylinder import BeamOptics
    from service.fitting import noise_model

    spec = request.calibration
    if spec is None:
        raise ValueError("a calibration sweep's request has no calibration spec")
    artefact = Artefact.from_dict(spec.artefact.model_dump())
    obs = Observations.from_raw(mapped.ranges, mapped.alpha, mapped.beta, mapped.motor_speed, source="sweep")
    optics = None
    if spec.optics == "lms1xx":
        o = config.scanner.optics
        optics = (
            BeamOptics()
            if config.optics_model == "ideal"
            else BeamOptics(exit_diameter_m=o.spot_exit_m, divergence_rad=o.divergence_rad)
        )
    options = CalibrationOptions(adjust=AdjustOptions(max_plane_points=spec.plane_points), optics=optics)
    result = calibrate([obs], artefact, nominal=mapped.rig, noise=noise_model(config), options=options)
    return {RESULT_KEY: result.to_dict(), "calibration_beams": len(obs)}


def store_calibration(result: dict[str, Any], ctx: JobContext, store: CalibrationStore, rig_id: str) -> dict[str, Any]:
    """The job's result for a calibration sweep's computed calibration: the whole calibration
    replaced by ``calibration_id``, ``calibration_active`` and its summary
    (``calibration_summary``, ``identifiability``). The calibration (its sources: the measurement)
    is stored, and activated when the request says so, by ``ctx.finish_also``: in the transaction
    that marks the job done, so a calibration is stored with its job done or not at all.
    :class:`service.errors.ServiceError` when the result holds no valid calibration."""
    from lrms.calibration import CalibrationError
    from service.calstore import StoredCalibration, new_id, parse_calibration
    from service.errors import ServiceError

    spec = ctx.request.calibration
    data = result.pop(RESULT_KEY, None)
    if spec is None or data is None:
        raise ServiceError("the calibration sweep's adjustment returned no calibration")
    try:
        cal = parse_calibration(data)
    except CalibrationError as exc:
        raise ServiceError(f"the calibration sweep's calibration is not valid: {exc}") from None
    cal = dataclasses.replace(cal, sources=(f"measurement {ctx.measurement.id}",))
    cid = new_id()

    def store_it(conn: Any) -> None:
        store.add_in(conn, cal, name=spec.name, comment=spec.comment, rig_id=rig_id, cid=cid, activate=spec.activate)

    ctx.finish_also = store_it
    summary = StoredCalibration(cid, "", spec.name, spec.comment, rig_id, spec.activate, cal).summary()
    result.update(
        calibration_id=cid,
        calibration_active=spec.activate,
        calibration_summary={k: summary[k] for k in ("estimated", "held", "model", "residuals")},
        identifiability=cal.identifiability.to_dict(),
    )
    return result
