"""Recordings of a run as MCAP files (``floornav run --record FILE.mcap``), with Foxglove
schemas so Foxglove opens them as they are, and their replay through the pipeline
(``[camera] source = "replay"``, ``device = "FILE.mcap"``).

- `app.recording.schemas`: the JSON schemas of the recorded messages.
- `app.recording.mcap_writer`: `McapRecorder`, the non-blocking writer (a bounded queue to
  a writer thread), and the message encoders.
- `app.recording.mcap_reader`: reading a recording back, complete or cut short.
- `app.recording.service`: the daemon's recording `Service` (reads the runtime's slots
  the way the web does).

The writer and reader depend on no device, simulator or server.
"""
