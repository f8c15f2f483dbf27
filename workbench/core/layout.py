"""The names of the files in an incident folder (docs/formats.md). :class:`workbench.project.Project` resolves
them; the modules that read or write a file take its name from here."""

from pathlib import Path

# the shipped carriage types, one TOML file each, named by the type's id (``<id>.toml``)
LIBRARY_TYPES_DIR = Path(__file__).resolve().parents[1] / "rolling_stock" / "types"

SETTINGS_FILE = "project.toml"
CAMERAS_FILE = "cameras.json"  # known cameras (hand-written) or the georef stage's output
CORRESPONDENCES_FILE = "correspondences.json"  # marked-point picks and rejections, or the correspond stage's merge
CONTROL_POINTS_FILE = "control_points.json"  # ground control points
