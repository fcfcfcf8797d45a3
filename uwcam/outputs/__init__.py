"""Outputs of the frame loop: each a subscriber to the published result with its own bounded
hand-off, thread and health (recorder, Foxglove server, ...), one per file."""
