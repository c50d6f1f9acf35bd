"""The spatiotemporal force regressor, material compensation, force metrics and the force
nodes (own, transfer, studies).  Modules: model (network, prediction, serialisation), train,
compensation, metrics, nodes.  Importing the package imports nothing heavy."""
