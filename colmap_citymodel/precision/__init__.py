"""s0, global test, covariances, variance components, check points, the quality verdict, and the
reports and plots of them."""
