"""The embedded town: a numpy simulator of CARLA-like towns, in three parts around `world.EmbeddedWorld`.

- `map`: the static town, from layout files (JSON, `map/maps/`) to the lane graph, routes with road options,
  scenery, buildings, regions and walkways (`map.town.get_town` builds and caches it)
- `traffic`: the other road users: signal phases (`lights`), IDM vehicles (`vehicles`), pedestrians
- `render`: what a camera sees (camera model, static-scene meshes, haze and rain, the Panda3D
  `CameraRenderer`) and the bird's-eye map drawing
- `dynamics`: the ego's bicycle model; `world`: `EmbeddedWorld`, one step of all of these, judged by
  `yawil.sim.judge`
"""
