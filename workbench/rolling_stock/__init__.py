"""Rolling-stock library: parametric simplified models of rail vehicles (body, roof, ends, bogies, couplers),
each with a painted livery texture and 7-10 named marked points, in the carriage frame.

Carriage frame: metres; x forward (towards the front coupler), y left, z up; origin on the centre line,
midway between the coupler faces, at top-of-rail height. A type is one TOML file (see :mod:`.spec`):
parametric (built from its dimensions) or a mesh type (a glTF/OBJ/STL file, e.g. a CAD export:
:mod:`.mesh_type`); the shipped ones live in ``types/``, users add their own in extra folders::

    from workbench.rolling_stock import load_library, get_type
    ct = get_type("shoreliner", extra_dirs=[incident / "rolling_stock"])
    mesh = ct.mesh(car_number="6221")        # textured trimesh, carriage frame
"""

from .library import TYPES_DIR, CarriageType, get_type, load_library, load_specs
from .spec import CarriageSpec, load_spec

__all__ = ["CarriageType", "CarriageSpec", "get_type", "load_library", "load_spec", "load_specs", "TYPES_DIR"]
