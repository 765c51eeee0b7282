// placeholder: pose_graph (being written)
