"""Sensor designs: one TOML file per skin module, read by the pipeline and the twin.

A design fixes the marker pattern, the skin and pin dimensions, the optical stack between the
cameras and the skin, and the nominal cameras. Files live in ``sim_assets/designs``; a user may
also pass a path to their own file. A file may build on a base (``extends = "base/stereotactip_module"``,
the StereoTacTip module shared by the stereo designs): see :func:`load_design` for the merge rule.

Sensor frame (all 3-D output of the project, mm): origin at the centre of the undeformed outer
skin surface, +z out of the skin toward the object, x along the camera baseline (left camera at
negative x), y = z × x. The cameras sit below the skin (negative z) and look along +z. Their
OpenCV axes (x right, y down, z forward) coincide with the sensor axes up to the toe-in, so image
``u`` grows with sensor x and ``v`` with sensor y.

Stack, from the object inward (rest state)::

    z = 0                     outer skin surface
    z = -T                    skin underside / top of the gel
    z = -(T + H)              marker faces (pin tips), H = pin height
    z = -(T + G)              gel / acrylic interface, G = gel thickness
    z = -(T + G + A)          acrylic / air interface, A = acrylic thickness
    z = -(T + G + A + air)    camera centres

Canonical marker order (the ids shared by the design, the pipeline's DTRC and the twin's truth):
rings from the outermost (layer m-1) to the centre (layer 0); within a ring counter-clockwise in the
sensor x-y plane (which is also counter-clockwise in atan2(v, u) of the image), starting at the
marker whose polar angle about the ring's centroid is closest to 0 (the +x direction).

Modules: :mod:`.schema` (one dataclass per TOML table), :mod:`.sensor` (:class:`SensorDesign` and its
derived geometry), :mod:`.layout` (marker patterns), :mod:`.validation` (a parsed mapping checked and
built), :mod:`.loading` (files, built-in names, ``extends`` chains) and :mod:`.writing` (mapping, digest,
TOML text).
"""

from pipeline.design.layout import analytic_pattern_radius_mm, marker_layout
from pipeline.design.loading import DEFAULT_DESIGN, design_path, list_designs, load_design
from pipeline.design.schema import (PATTERN_KINDS, PATTERN_MAPPINGS, TWIN_KEYS, Camera, Cameras, DesignError, Gel,
                                    Markers, MonoCamera, Optics, Pattern, Pins, Skin)
from pipeline.design.sensor import SensorDesign
from pipeline.design.validation import MAX_FRICTION, design_from_dict
from pipeline.design.writing import design_digest, mapping_to_toml, to_dict, to_toml

__all__ = [
    "DEFAULT_DESIGN",
    "PATTERN_KINDS",
    "PATTERN_MAPPINGS",
    "TWIN_KEYS",
    "MAX_FRICTION",
    "DesignError",
    "Pattern",
    "Skin",
    "Pins",
    "Markers",
    "Optics",
    "Gel",
    "Camera",
    "Cameras",
    "MonoCamera",
    "SensorDesign",
    "load_design",
    "list_designs",
    "design_path",
    "design_from_dict",
    "marker_layout",
    "analytic_pattern_radius_mm",
    "to_dict",
    "to_toml",
    "mapping_to_toml",
    "design_digest",
]
