"""Camera calibration (`roadsurf calibrate`): intrinsics and lens distortion from checkerboard
or ChArUco photographs, camera height and mount angles from a board lying on the road, written
as a drive's camera.yaml. Modules: board (spec, corners, texture), detect, intrinsics, mount,
command (the CLI's function), synthetic (rendered boards with known truth)."""
