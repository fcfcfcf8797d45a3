"""The topside fleet view: every vehicle publishing on Zenoh, watched from one page (docs/architecture.md)."""
