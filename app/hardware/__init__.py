"""Robot hardware behind small interfaces: the Uno's serial protocol and link, cameras."""
