"""Ray-casting simulator of the SOTIF highway use case, writing KITTI data sets."""
