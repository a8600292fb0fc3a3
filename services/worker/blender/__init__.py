"""The only bpy-importing part of the service: build a space's scene and render views to pass sets.

Import it lazily (`from services.worker.blender import BlenderScene`) where a render is needed: importing bpy
takes about a second and a few hundred MB.
"""

from services.worker.blender.render import DEVICES, RenderOptions, srgb_encode
from services.worker.blender.scene import BlenderScene, srgb_to_linear

__all__ = ["DEVICES", "BlenderScene", "RenderOptions", "srgb_encode", "srgb_to_linear"]
