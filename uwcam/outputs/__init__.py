"""Outputs: independent subscribers to the frame loop's published results.

Each output gets every published frame through ``pipeline.subscribe``, keeps only the newest
in its own one-slot hand-off, does its work in its own thread and reports its own health, so a
slow or failing output never holds the loop or another output.
"""
