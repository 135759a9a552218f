"""How the simulated camera sees the pouch: the frame's composition (``render``), the LEDs
(``light``), the camera's mounting, exposure and blur (``camera``) and its fisheye lens
(``fisheye``). See ``docs/simulator.md``."""
