"""The web page's live view: the replay's overlay (service/tools/annotate.py) on a daemon frame.

ROI grid coloured by what each ROI contributed, the mesh cells and parallelograms, the net's
axes and normal back-projected through the calibration, and the distance, tilt, confidence,
filter state and the distance the autopilot was handed (which may be another one: along the
camera axis) as text, net damage (candidates yellow, confirmed holes red): the picture
`netpose replay` writes, drawn on the newest frame only
when a page is open (drivers/web draws at `web.live_hz` on its own thread).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.pipeline import PipelineResult
from service.tools.annotate import FrameAnnotator


class LiveView:
    """Draws (frame, PipelineResult) at most `width` pixels wide; one per camera."""

    def __init__(self, camera: CameraModel, width: int) -> None:
        self._annotator = FrameAnnotator(camera, width=width)

    def __call__(self, frame: Any, result: PipelineResult) -> npt.NDArray[np.uint8]:
        color = getattr(frame, "color", None)
        image = color if color is not None else frame.image
        return self._annotator.annotate(image, result.estimate, track=result.track,
                                        label=f"frame {frame.index}", refused=result.error,
                                        damage=result.damage, sent=result.reading)
