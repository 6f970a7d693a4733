"""Fitting anisotropic BTFs to HDR multi-light captures (paper 004, sections 3.1-3.2)."""
from .capture import Capture as Capture
from .capture import CaptureError as CaptureError
from .capture import load_capture as load_capture
from .hdr import Observations as Observations
from .hdr import merge_capture as merge_capture
from .hdr import merge_exposures as merge_exposures
from .synth import EXPOSURES_S as EXPOSURES_S
from .synth import LIGHT_DIRECTIONS as LIGHT_DIRECTIONS
from .synth import Sensor as Sensor
from .synth import paper_light_angles as paper_light_angles
from .synth import paper_light_directions as paper_light_directions
from .synth import stratified_light_subset as stratified_light_subset
from .synth import synth_capture as synth_capture
from .synth import synth_maps as synth_maps
from .synth import synth_observations as synth_observations
