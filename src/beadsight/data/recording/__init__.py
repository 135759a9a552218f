"""Raw recording sessions: this project's folder format (writer + reader) and the reference's.

This project's format (``docs/recording-format.md``) is a folder::

    session.json      metadata, written first, replaced atomically on every update
    video_0000.avi    MJPG video in chunks of ``chunk_frames`` frames (~1 s each)
    frames.csv        chunk,index,t_unix,t_mono,camera_index   (one row per frame)
    force.csv         t_unix,t_mono,grams,seq,device_ms        (one row per scale reading)
    printer.csv       t_unix,t_mono,gcode,x,y,z,press          (one row per executed command)
    events.jsonl      {"event": ..., "t_unix": ..., "t_mono": ..., ...} per line

Files are appended as data arrives, flushed and fsync'ed at every chunk boundary,
so a crash loses at most the last chunk (about one second).

The **reference raw format** (reference-facts section 5) is a folder with
``video_k.avi`` + ``video_log_k.txt`` (``unix_time,frame_number,video_path``),
``force_log.txt`` (``unix_time,value``, no header), ``printer_log.txt`` (records
ending with ``\\r``: ``unix_time,x,y,gcode`` with several G-code lines in ``gcode``;
x = y = -1 for non-data moves) and ``experiment_parameters.json``.

:func:`open_recording` reads either into one :class:`Recording`. A last line
without its line terminator (a crash mid-write), unparsable lines, and frames
listed but missing from a truncated video are tolerated and listed in
``Recording.warnings``, each naming its file and lines.

Modules: :mod:`.logs` (the streams and file names), :mod:`.text` (parsing the logs),
:mod:`.ours` and :mod:`.reference` (the two readers), :mod:`.reader`
(:func:`open_recording`), :mod:`.video` (reading videos), :mod:`.avi` (the MJPG
muxer) and :mod:`.writer` (:class:`RecordingWriter`).
"""

from beadsight.config import REFERENCE_CENTRE_XY_MM
from beadsight.data.recording import logs
from beadsight.data.recording.avi import MjpgAviWriter
from beadsight.data.recording.logs import *  # noqa: F403  (the names in logs.__all__)
from beadsight.data.recording.reader import detect_format, open_recording
from beadsight.data.recording.text import read_events, read_session
from beadsight.data.recording.video import is_mjpg, iter_video
from beadsight.data.recording.writer import RecordingWriter

__all__ = [
    *logs.__all__,
    "REFERENCE_CENTRE_XY_MM",
    "MjpgAviWriter",
    "RecordingWriter",
    "detect_format",
    "is_mjpg",
    "iter_video",
    "open_recording",
    "read_events",
    "read_session",
]
