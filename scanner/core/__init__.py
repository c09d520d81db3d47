"""The ground floor: frames and transforms, camera model, target specs, images, tolerances, configs, files, worker pools.

Imports nothing of this project above it."""
