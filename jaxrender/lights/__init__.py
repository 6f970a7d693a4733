"""Light sources: spot lights (cone, falloff, projected light map), the sun, environment maps
with importance sampling. One private module per kind; public names re-exported here."""

from ._envmap import EnvMap as EnvMap
from ._envmap import EnvSamples as EnvSamples
from ._envmap import env_pdf as env_pdf
from ._envmap import env_radiance as env_radiance
from ._envmap import env_texel_solid_angles as env_texel_solid_angles
from ._envmap import envmap_direction as envmap_direction
from ._envmap import envmap_uv as envmap_uv
from ._envmap import load_envmap as load_envmap
from ._envmap import sample_envmap as sample_envmap
from ._quad import QuadLights as QuadLights
from ._quad import QuadLightSamples as QuadLightSamples
from ._quad import quad_light_radiance_at as quad_light_radiance_at
from ._quad import sample_quad_lights as sample_quad_lights
from ._spot import SpotLight as SpotLight
from ._spot import stack_spotlights as stack_spotlights
from ._spot import unstack_spotlights as unstack_spotlights
from ._sun import Sun as Sun
from ._sun import sun_direction_z_up as sun_direction_z_up
