"""The perception core: local features, matching, compatibility neighbours, NM-Net, the correspondence selectors,
two-view geometry and :class:`~nmnet_ros.core.pipeline.Frontend`, which runs them on a frame. Imports no ROS and
reads no recordings."""
