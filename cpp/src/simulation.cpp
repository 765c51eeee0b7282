// placeholder: simulation (being written)
