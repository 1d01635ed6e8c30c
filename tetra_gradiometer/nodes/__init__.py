"""ROS 2 nodes: driver, tensor, calibrator, compensator, target (thin: message -> array ->
core -> message), their shared helpers (``common``, ``managed``, ``process``), and what only
the nodes use: the driver's frame sources (``replay``; ``rosbags`` imported only to replay a
bag), the target node's live track (``track``) and its messages (``target_messages``).

Layering: a node imports ``core``, ``io`` and the ``pipelines`` that need no offline-only
package (``window_check``), never ``reports`` or ``cli``; it starts on a rosdep-only install
(no ``rosbags``, ``ppigrf``, ``dask``, and no ``matplotlib`` on its path).
"""
