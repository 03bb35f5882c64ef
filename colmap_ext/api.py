"""`incremental_mapping`: `pycolmap.incremental_mapping`'s call with our mapper behind it,
so that code written for pycolmap switches by changing one import."""

from __future__ import annotations

from pathlib import Path

import pycolmap

from colmap_ext.mapper.flags import pycolmap_options
from colmap_ext.mapper.options import MapperOptions
from colmap_ext.mapper.pipeline import run


def incremental_mapping(database_path: str | Path, image_path: str | Path,
                        output_path: str | Path,
                        options: pycolmap.IncrementalPipelineOptions | MapperOptions | None = None,
                        input_path: str | Path | None = None,
                        ) -> dict[int, pycolmap.Reconstruction]:
    """Reconstruct into OUTPUT/0, OUTPUT/1, ... and return the models by index, as
    pycolmap does (models already there are replaced; a numbered folder there that is no
    model is not, and the call refuses); with `input_path`, continue that
    model. A pycolmap options object is read through the option table (mapper/flags.py):
    every value it holds is applied, so a default-constructed one carries COLMAP's
    thresholds, except its intrinsics refinement (flags.pycolmap_options); None gives our
    defaults. Its `image_names` selects the images. The database is read, never written."""
    image_names = None
    if isinstance(options, pycolmap.IncrementalPipelineOptions):
        image_names = list(options.image_names) or None
        options = pycolmap_options(options)
    return run(database_path, image_path, output_path, options or MapperOptions(),
               overwrite=True, image_names=image_names, input_path=input_path)
