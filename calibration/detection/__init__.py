"""Target detection: the concentric-circles target, chessboards and circle grids, conics and labelled observations."""
