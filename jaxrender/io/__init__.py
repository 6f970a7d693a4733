"""File I/O at the edge of the toolkit: EXR (OpenEXR), PNG (scikit-image), BTF directories,
BVH motion capture, colour transfer functions and tone mapping, atomic writes, output locks, and the
error types."""

from ..errors import InputError as InputError
from ..errors import InputErrors as InputErrors
from ..errors import OutputBusy as OutputBusy
from ._atomic import atomic_path as atomic_path
from ._atomic import remove_temporaries as remove_temporaries
from ._btf import BTF_FORMAT as BTF_FORMAT
from ._btf import BTF_VERSION as BTF_VERSION
from ._btf import LEVEL0_CHANNELS as LEVEL0_CHANNELS
from ._btf import LEVEL_CHANNELS as LEVEL_CHANNELS
from ._btf import LOBE_CHANNELS as LOBE_CHANNELS
from ._btf import MASK_CHANNEL as MASK_CHANNEL
from ._btf import btf_level_name as btf_level_name
from ._btf import complete_level as complete_level
from ._btf import read_btf as read_btf
from ._btf import write_btf as write_btf
from ._btf import write_btf_levels as write_btf_levels
from ._btf import write_btf_previews as write_btf_previews
from ._bvh import CHANNEL_NAMES as CHANNEL_NAMES
from ._bvh import BVHMotion as BVHMotion
from ._bvh import read_bvh as read_bvh
from ._bvh import write_bvh as write_bvh
from ._color import linear_to_srgb as linear_to_srgb
from ._color import luminance as luminance
from ._color import srgb_to_linear as srgb_to_linear
from ._color import tonemap as tonemap
from ._fields import MAX_PROBLEMS as MAX_PROBLEMS
from ._fields import Fields as Fields
from ._fields import Problems as Problems
from ._fields import is_number as is_number
from ._headers import IMAGE_SUFFIXES as IMAGE_SUFFIXES
from ._headers import SUPPORTED_IMAGES as SUPPORTED_IMAGES
from ._headers import ImageHeader as ImageHeader
from ._headers import image_header as image_header
from ._images import read_exr as read_exr
from ._images import read_image as read_image
from ._images import write_exr as write_exr
from ._images import write_image as write_image
from ._images import write_png as write_png
from ._lock import LOCK_NAME as LOCK_NAME
from ._lock import lock_owner as lock_owner
from ._lock import output_lock as output_lock
from ._mat import read_mat as read_mat
