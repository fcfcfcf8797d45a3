"""The frame loop's stages, one per file, in the order a frame meets them (docs/architecture.md)."""
