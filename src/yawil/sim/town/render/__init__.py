"""What the embedded town looks like: the camera model and protocol projection (`camera`), static-scene
meshes (`scene_mesh`), haze and rain in numpy (`weather_fx`), the Panda3D offscreen `CameraRenderer`
(`renderer`, software rendering by default), and bird's-eye map drawing with matplotlib (`birdseye`)."""
