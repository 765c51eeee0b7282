// placeholder: mapper (being written)
