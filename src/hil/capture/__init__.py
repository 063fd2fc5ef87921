"""Capture files: what the daemons record, and the one reader of it.

* :mod:`hil.capture.schema`: the files of a capture directory, a function that builds each
  record, and the key that joins the RVE's records with the OBU's.
* :mod:`hil.capture.writers`: append-only writers (JSON lines, plain or in one gzip
  stream, pcapng, CAN logs), flushed once per tick, so a killed daemon keeps all but its
  last tick.
* :mod:`hil.capture.tracks`: ``obu.tracks.bin``, every tracked RV at every tick as what
  changed since the tick before.
* :mod:`hil.capture.reader`: a capture directory read back as streams, checked, up to a
  torn tail.
"""

from hil.capture import schema
from hil.capture.reader import (
    Capture,
    CaptureError,
    Torn,
    clock_offset,
    gunzip,
    iter_lines,
    read_capture,
    read_json,
    read_lines,
    read_rx,
    read_tracks,
    segment_files,
    torn_line,
    truth_in_frame,
)
from hil.capture.tracks import TrackBlock, TrackWriter, block_rows, iter_blocks, read_columns
from hil.capture.writers import (
    CanLogs,
    GzipJsonLines,
    JsonLines,
    PcapngWriter,
    can_log,
    claim,
    ethernet,
    finish,
    udp_packet,
    versions,
)

__all__ = ["CanLogs", "Capture", "CaptureError", "GzipJsonLines", "JsonLines", "PcapngWriter",
           "Torn", "TrackBlock", "TrackWriter", "block_rows", "can_log", "claim",
           "clock_offset", "ethernet", "finish", "gunzip", "iter_blocks", "iter_lines",
           "read_capture", "read_columns", "read_json", "read_lines", "read_rx", "read_tracks",
           "schema", "segment_files", "torn_line", "truth_in_frame", "udp_packet", "versions"]

