"""The calibration rig: press plans and collection from a printer, a scale and a camera."""
