"""The embedded ``lite`` backend: lane-graph maps, kinematic traffic, Panda3D offscreen camera."""
