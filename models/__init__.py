"""Models: the distance net (training, TorchScript export, loading with a footprint check).

Kept free of heavy imports so that `dct models --help` stays fast; import
`models.distance_net.DistanceNet` (torch) and `models.footprint_dual` (numpy) directly.
"""
