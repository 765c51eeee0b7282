// placeholder: evaluation (being written)
