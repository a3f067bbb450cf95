"""The world the robots map: floor plans of every kind (floorplan, cubicasa, plans), paths, the
LiDAR sensor model (sensing), recordings, real LiDAR logs (datasets) and the log-odds reference
(logodds), and where the robots have seen (unseen)."""
