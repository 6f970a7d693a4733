"""File I/O at the edge of the toolkit: EXR (OpenEXR), PNG (scikit-image), BTF directories,
colour transfer functions and tone mapping, atomic writes, and the user-input error type."""

from ._atomic import atomic_path as atomic_path
from ._color import linear_to_srgb as linear_to_srgb
from ._color import luminance as luminance
from ._color import srgb_to_linear as srgb_to_linear
from ._color import tonemap as tonemap
from ._errors import InputError as InputError
from ._images import read_exr as read_exr
from ._images import read_image as read_image
from ._images import write_exr as write_exr
from ._images import write_image as write_image
from ._images import write_png as write_png
