"""A vehicle's onboard loop: detections -> projection lines -> durable queue -> upload.

The paper's onboard block (perception output + GNSS -> geolocated feature marks,
"registered on the vehicle and uploaded to cloud servers whenever possible"). A vehicle
that follows the map also reports, per pass, the mapped signs it had in view and did not
detect (issue 21: :mod:`vehicle.absence_report`), queued and uploaded with the pass.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import zenoh

from schemas import Absences, Observations
from schemas.map import MapLandmarks
from vehicle.absence_report import DEFAULT_ABSENCE, AbsenceConfig, pass_absences
from vehicle.geoloc import (
    DEFAULT_TIMING,
    Detections,
    FixCheck,
    GnssFixes,
    ProjectionLines,
    VehicleModel,
    detection_reach,
    fix_outliers,
    geolocate,
)
from vehicle.mapclient import MapClient
from vehicle.pitch import measured_sigma_el
from vehicle.pose import PoseTiming
from vehicle.tracking import TrackConfig, smoothed_rays, track_rays
from vehicle.uploader import Uploader, UploadResult

DEFAULT_FIX_CHECK = FixCheck()
DEFAULT_TRACKING = TrackConfig()


def to_observations(
    lines: ProjectionLines, obs_id: np.ndarray, track: np.ndarray | None = None
) -> Observations:
    """Projection lines -> the wire table (ids assigned by the vehicle; tracks optional)."""
    return Observations(
        obs_id=np.asarray(obs_id, np.uint64),
        t=lines.t,
        image=lines.image.astype(np.uint32),
        sign_class=lines.sign_class.astype(np.uint16),
        lat=lines.lat,
        lon=lines.lon,
        h=lines.h,
        direction=lines.direction,
        sigma_az=lines.sigma_az,
        sigma_el=lines.sigma_el,
        sigma_pos_h=lines.sigma_pos_h,
        sigma_pos_v=lines.sigma_pos_v,
        range_m=lines.range_m,
        sigma_range_m=lines.sigma_range_m,
        score=lines.score.astype(np.float32),
        track=None if track is None else np.asarray(track, np.uint32),
    )


class VehicleAgent:
    """One vehicle: its calibration and its store-and-forward upload stream."""

    def __init__(
        self,
        vehicle_id: str,
        model: VehicleModel,
        queue_dir: str | Path,
        batch_size: int = 500,
        fix_check: FixCheck | None = DEFAULT_FIX_CHECK,
        tracking: TrackConfig | None = DEFAULT_TRACKING,
        timing: PoseTiming = DEFAULT_TIMING,
        absence: AbsenceConfig = DEFAULT_ABSENCE,
    ):
        self.vehicle_id = vehicle_id
        self.model = model
        self.fix_check = fix_check
        """Drop detections of fixes that jump off the track (None: keep every one)."""
        self.tracking = tracking
        """Label detections of one sign followed through the frames (None: untracked)."""
        self.timing = timing
        """How a detection's pose is interpolated from the fixes (:mod:`vehicle.pose`)."""
        self.absence = absence
        """Which mapped signs a pass should have seen (:mod:`vehicle.absence_report`)."""
        self.uploader = Uploader(vehicle_id, Path(queue_dir) / f"{vehicle_id}.sqlite", batch_size)
        self.last_kept = np.zeros(0, bool)
        """Per detection of the last :meth:`record`, whether it was queued."""
        self.dropped = 0
        """Detections dropped so far: of a suspect fix, or (timed detections) with no
        usable fix within ``timing.max_gap_s``."""
        self.dropped_gap = 0
        """Of those, timed detections with no usable fix near enough (never extrapolated)."""
        self.last_pitch_sigma_rad = model.pitch_sigma_rad
        """The white pitch std the last tracked :meth:`record` measured from its tracks and
        put into its rays' elevation sigmas (:mod:`vehicle.pitch`; the model's bound when
        the pass had too few)."""
        self.last_absences = Absences.empty()
        """The absences the last :meth:`record` queued (none without ``expected_map``)."""

    def record(
        self,
        pass_id: int,
        fixes: GnssFixes,
        det: Detections,
        expected_map: MapLandmarks | None = None,
    ) -> Observations:
        """Geolocate a pass's detections and queue them (durably, before any upload).

        Suspect fixes (:func:`fix_outliers`) are not used: with detection times
        (``det.t``) the poses are interpolated from the other fixes, and a detection no
        remaining fix reaches within ``timing.max_gap_s`` is dropped (``dropped_gap``);
        without times (one fix per image) a suspect fix's detections are dropped.
        :attr:`last_kept` says which detections were queued, in ``det``'s row order.
        With tracking, the elevation sigmas carry the pitch measured from the pass's own
        tracks instead of the model's bound (:mod:`vehicle.pitch`).

        With ``expected_map`` (the map's landmarks near the pass's route, e.g.
        :meth:`MapClient.near`), the pass's absences (:func:`pass_absences`: the whole pass
        in one call) are queued with its observations, in one transaction, and kept in
        :attr:`last_absences`; they are uploaded once, with the pass's last batch."""
        keep = np.ones(len(det), bool)
        bad_fix = None
        use = fixes
        if self.fix_check is not None and len(det):
            bad_fix = fix_outliers(fixes, self.fix_check)
            if det.t is None:
                keep = ~bad_fix[np.asarray(det.image, np.int64)]
            else:
                use, bad_fix = fixes.take(np.flatnonzero(~bad_fix)), None
        if det.t is not None and len(det):
            reach = detection_reach(use, det, self.timing) if len(use) else np.zeros(len(det), bool)
            self.dropped_gap += int((keep & ~reach).sum())
            keep &= reach
        lines = geolocate(use, det.take(np.flatnonzero(keep)), self.model, timing=self.timing)
        self.last_kept = keep
        self.dropped += int((~keep).sum())
        track = None
        if self.tracking is not None and len(lines):
            rays = smoothed_rays(use, lines, self.tracking, bad_fix, timing=self.timing)
            track = track_rays(rays, self.tracking)
            sigma_el, self.last_pitch_sigma_rad = measured_sigma_el(
                lines.t,
                lines.direction,
                lines.sigma_el,
                lines.range_m,
                track,
                self.model.pitch_sigma_rad,
            )
            lines = replace(lines, sigma_el=sigma_el)
        absences = Absences.empty()
        if expected_map is not None:
            absences = pass_absences(
                fixes, det, expected_map, self.model, self.absence, self.timing, self.fix_check
            )
        self.last_absences = absences
        obs = to_observations(lines, self.uploader.next_obs_ids(len(lines)), track)
        self.uploader.enqueue(pass_id, obs, absences)
        return obs

    def upload(self, session: zenoh.Session, timeout: float = 10.0) -> UploadResult:
        return self.uploader.flush(session, timeout)

    def map_client(self, session: zenoh.Session, radius_m: float = 500.0) -> MapClient:
        """This vehicle's map client: it asks for snapshots under the vehicle id (the key
        the publisher limits per client, and the only one it may query in secured mode).
        The caller closes it."""
        return MapClient(session, radius_m=radius_m, client_id=self.vehicle_id)

    def close(self) -> None:
        self.uploader.close()
