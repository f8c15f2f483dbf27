"""Desktop viewer of a reconstructed incident (Open3D GUI): ``workbench view projects/NAME``."""
