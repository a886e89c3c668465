"""The simulated world: a floor plan (`world`), a differential-drive robot that a
simulated Uno drives (`robot`), and a camera renderer with ground truth (`render`)."""
