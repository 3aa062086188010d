"""Module 9's plots: plant rows to plot rows - the plot table, where the plots are, crop rows within a plot,
the field figure, field books, and the ``plots`` settings section."""
