"""Simulated image-based camera rig behind the CameraRig protocol (driver ``sim_images``).

`SimCameraRig` renders the eight synthetic images of the marker cluster (sim.camera_rig) for the
actual tool pose and runs the real processing pipeline (drivers.mvs) on them, returning the
TCP/SMR point in the MVS frame (the rig's own frame, with its small scale error) with its
covariance, quality and, when refused, the reason."""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import Lifecycle, RigReading, reject_keys
from drivers.mvs import MarkerTracker, RigModel
from dt_kernel.config import Frozen
from dt_kernel.errors import DriverError
from sim.camera_rig import DEFAULT_CONFIG, Occluder, RigConfig, SimCameraImages, load_rig_config, validate_rig


class CameraOptions(Frozen):
    """The runtime YAML's options of the image rig: render settings over configs/cameras.yaml's
    (checked against sim.camera_rig's model in `configure`) and the rendering's seed."""

    render: dict[str, Any] = {}
    seed: int = 0


PoseFn = Callable[[], tuple[np.ndarray, np.ndarray]]


class SimCameraRig(Lifecycle):
    """CameraRig over synthetic images and the OpenCV processing pipeline.

    Parameters
    ----------
    tool_pose: callable -> (R (3,3), p (3,)) ACTUAL tool orientation and TCP, WORLD frame, m.
        Optional when `world` (a drivers.simulated.SimWorld) is given: then world.tool_pose.
    config: path of configs/cameras.yaml (default) or a validated sim.camera_rig.RigConfig.
    seed: seeds every random draw of the rendering (same seed -> same readings).
    occluded: optional `occluded(cam_center (3,), points (n,3)) -> bool (n,)` (world frame),
        e.g. PyBullet ray tests against the arm's links.
    predicted_pose: optional callable -> (R, p) the twin's predicted tool pose in the WORLD
        frame; mapped into the MVS frame with the rig's nominal placement (config rig_pose) to
        place the regions of interest. Without it, the rig finds the cluster by epipolar
        matching on full frames (slower, same accuracy).
    clock: optional callable -> time stamp (s); default world.t, else frame index / 360 Hz.
    source: names the config in errors (the registry passes the runtime config's name).

    `configure({"render": {...}})` changes render settings (fault injection: spurious
    reflections, occlusions, dropped cameras, ...) before activation.
    """

    FRAME_RATE_HZ = 360.0
    needs_world = True  # built by the registry, it renders the simulated world's tool
    config_model = CameraOptions

    def __init__(self, tool_pose: PoseFn | None = None, config: str | Path | RigConfig = DEFAULT_CONFIG,
                 seed: int = 0, occluded: Occluder | None = None, predicted_pose: PoseFn | None = None,
                 world: Any = None, clock: Callable[[], float] | None = None,
                 source: str = "<SimCameraRig.configure>"):
        self._source = source
        if tool_pose is None:
            if world is None:
                raise DriverError("SimCameraRig needs tool_pose() or world")
            tool_pose = getattr(world, "tool_pose_seen_by_camera", world.tool_pose)
        if world is not None:
            predicted_pose = predicted_pose or getattr(world, "predicted_tool_pose", None)
            occluded = occluded or getattr(world, "occluded", None)
        if clock is None and world is not None:
            clock = lambda: float(world.t)  # noqa: E731
        self._tool_pose, self._predicted, self._occluded = tool_pose, predicted_pose, occluded
        self._clock = clock
        self.seed = int(seed)
        self.cfg = config if isinstance(config, RigConfig) else load_rig_config(config)
        self._frames = 0
        self._build()

    def _build(self) -> None:
        self.renderer = SimCameraImages(self.cfg, seed=self.seed, occluded=self._occluded)
        cams = [c.as_dict() for c in self.renderer.calibration()]
        self.model = RigModel.build(cams, self.cfg.markers.positions_m, self.cfg.markers.diameter_m,
                                    self.cfg.processing.model_dump())
        self.tracker = MarkerTracker(self.model)
        Rm, tm = self.cfg.rig_pose.matrix()
        self._Rm, self._tm, self._s = Rm, tm, self.cfg.scale_error
        self.last_images: list | None = None

    def _on_configure(self, config: dict[str, Any]) -> None:
        if not config:
            return
        reject_keys(config, self._source, ("render", "seed"), "the image camera rig")
        data = self.cfg.model_dump()
        data["render"].update(config.get("render", {}))
        self.cfg = validate_rig(data, self._source)
        self.seed = int(config.get("seed", self.seed))
        self._build()

    # ------------------------------------------------------------------ frames
    def world_to_mvs_nominal(self, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A world-frame tool pose in the MVS frame through the rig's nominal placement.

        Parameters
        ----------
        R : ndarray
            (3, 3), world frame.
        p : ndarray
            (3,) m, world frame.

        Returns
        -------
        R : ndarray
            (3, 3), MVS frame.
        p : ndarray
            (3,) m, MVS frame.
        """
        return self._Rm.T @ np.asarray(R, float), self._Rm.T @ (np.asarray(p, float) - self._tm)

    def truth_mvs(self) -> np.ndarray:
        """The true TCP in the MVS frame (with the rig's scale error), for scoring only."""
        _, p = self._tool_pose()
        return (1.0 + self._s) * self._Rm.T @ (np.asarray(p, float) - self._tm)

    def _now(self) -> float:
        return self._clock() if self._clock is not None else self._frames / self.FRAME_RATE_HZ

    def read(self) -> RigReading:
        """Render the frames for the actual tool pose and measure the TCP from them (m, MVS frame).

        The twin's predicted pose, when given to the rig, seeds the pipeline's ROI search; ``t`` is the
        rig's clock (s) and ``host_time`` the moment the frames were rendered.

        Returns
        -------
        RigReading
            Refused, with the pipeline's reason, when no measurement is reported.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When the rendering or the processing fails numerically.
        """
        self._require("active")
        try:
            R, p = self._tool_pose()
            images, _ = self.renderer.render(np.asarray(R, float), np.asarray(p, float))
            host_time = time.monotonic()  # the frames are in: what follows is our processing
            pred = None
            if self._predicted is not None:
                pred = self.world_to_mvs_nominal(*self._predicted())
            meas = self.tracker.measure(images, pred)
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise DriverError(f"simulated camera rig failed: {exc}") from exc
        self.last_images = images
        t = self._now()
        self._frames += 1
        q = dict(meas.quality)
        if not meas.ok:
            return RigReading(point=None, t=t, quality=q, refused=meas.refused, host_time=host_time)
        return RigReading(point=meas.tcp, t=t, cov=meas.cov, quality=q, host_time=host_time)
