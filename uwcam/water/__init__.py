"""The water's own light: the backscatter model, its compensation and the judge of which pixels rise clearly above it (docs/architecture.md)."""
