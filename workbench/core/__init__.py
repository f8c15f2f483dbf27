"""Floor 1: geometry, camera models, frames and settings. No file I/O beyond parsing."""
