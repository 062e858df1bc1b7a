"""pipescan's scan simulator: ray-cast LiDAR frames of a pipe with known defects
(:mod:`pipescan.simulator.scan`), written as an ordinary scan archive with its ground truth
beside it (:mod:`pipescan.simulator.archive`)."""
