"""tetra_gradiometer: vehicle interference compensation for a tetrahedral magnetic gradient
tensor system (after Yu et al. 2014), as a ROS-free core, ROS 2 nodes and offline tools."""

__version__ = '0.1.0'
