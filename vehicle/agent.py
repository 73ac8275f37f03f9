"""A vehicle's onboard loop: detections -> projection lines -> durable queue -> upload.

The paper's onboard block (perception output + GNSS -> geolocated feature marks,
"registered on the vehicle and uploaded to cloud servers whenever possible").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zenoh

from hdmap.geoloc import Detections, GnssFixes, ProjectionLines, VehicleModel, geolocate
from schemas import Observations
from vehicle.uploader import Uploader, UploadResult


def to_observations(lines: ProjectionLines, obs_id: np.ndarray) -> Observations:
    """Projection lines -> the wire table (ids assigned by the vehicle)."""
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
    )


class VehicleAgent:
    """One vehicle: its calibration and its store-and-forward upload stream."""

    def __init__(
        self, vehicle_id: str, model: VehicleModel, queue_dir: str | Path, batch_size: int = 500
    ):
        self.vehicle_id = vehicle_id
        self.model = model
        self.uploader = Uploader(vehicle_id, Path(queue_dir) / f"{vehicle_id}.sqlite", batch_size)

    def record(self, pass_id: int, fixes: GnssFixes, det: Detections) -> Observations:
        """Geolocate a pass's detections and queue them (durably, before any upload)."""
        lines = geolocate(fixes, det, self.model)
        obs = to_observations(lines, self.uploader.next_obs_ids(len(lines)))
        self.uploader.enqueue(pass_id, obs)
        return obs

    def upload(self, session: zenoh.Session, timeout: float = 10.0) -> UploadResult:
        return self.uploader.flush(session, timeout)

    def close(self) -> None:
        self.uploader.close()
