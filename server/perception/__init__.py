"""Server perception: segmentation / detection -> instances -> 3D object measurements."""
