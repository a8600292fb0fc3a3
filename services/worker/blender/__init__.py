"""The only bpy-importing part of the service: build a space's scene (scene.py) and render views to pass sets
(render.py); threads.py imports bpy with Blender's thread pool sized to the render budget.

Import the modules lazily where a render is needed: importing bpy takes about a second and a few hundred MB.
This package file imports nothing, so `services.worker.blender.threads` can import bpy first, its way.
"""
