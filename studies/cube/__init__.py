"""The cube-toss study: LCSs learned from the 550 real ContactNets cube tosses against affine and
MLP baselines along a learning curve (:mod:`studies.cube.study`)."""
