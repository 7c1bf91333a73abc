"""Sources: the episode record, readers for the OpenDV / NAVSIM / CARLA layouts, the synthetic world."""
