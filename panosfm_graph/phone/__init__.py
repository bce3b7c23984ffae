"""A phone's own recording -> a capture: video + raw gyroscope / accelerometer logs (``panosfm import``, issue #41).

:func:`import_capture` (start reading here) writes a capture directory in
``capture-format.md`` from a video and a sensor log; :func:`format_import`
is its CLI report. One module per step:

* :mod:`.logs`: the sensor log layouts (generic CSV, Sensor Logger, phyphox) -> :class:`RawSensors`;
* :mod:`.video_rotation`: the camera's turn between consecutive frames, from feature flow;
* :mod:`.sync`: the video-to-sensor time offset and the camera's axes in the phone's;
* :mod:`.attitude`: the attitude at every frame, a GTSAM AHRS smoother (gyroscope bias included);
* :mod:`.line_timing`: the time offset from the lines' rotations, where the turns leave it loose (a smooth spin);
* :mod:`.importer`: the steps in order, the files written.
"""
from .attitude import Attitude, smooth_attitude
from .importer import ImportResult, format_import, import_capture
from .line_timing import LineTiming, retime_by_lines
from .logs import FORMATS, RawSensors, read_sensors
from .sync import Sync, estimate_sync
from .video_rotation import frame_rotations

__all__ = ["Attitude", "smooth_attitude", "ImportResult", "format_import", "import_capture", "LineTiming",
           "retime_by_lines", "FORMATS",
           "RawSensors", "read_sensors", "Sync", "estimate_sync", "frame_rotations"]
