"""The ``terrain`` stage: the DEM and the buildings as meshes in the scene frame (the DEM itself is read by
:mod:`workbench.files.dem`)."""
