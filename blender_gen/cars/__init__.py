"""Where cars come from: the procedural body (`spec`, `body`), the named catalogue and the
`--cars` selectors (`catalogue`), unlimited seeded cars (`sampler`), silhouettes for
measuring shape diversity (`silhouette`), and real models with their part rules
(`rules`, `importer`; the importer imports bpy, the rest does not).
"""
from .body import build_car
from .catalogue import CATALOGUE_FILE, load_catalogue, load_part_materials
from .selectors import RandomCars, select_cars
from .identity import catalogue_digest
from .spec import CATEGORIES, PARTS, STYLES, CarSpec, spec_problems

__all__ = ["CATALOGUE_FILE", "CATEGORIES", "PARTS", "STYLES", "CarSpec", "RandomCars", "build_car",
           "catalogue_digest", "load_catalogue", "load_part_materials", "select_cars", "spec_problems"]
