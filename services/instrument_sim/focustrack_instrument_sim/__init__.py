"""The simulated microscope: surfaces, specimen, optics, camera and stage, on Zenoh."""
