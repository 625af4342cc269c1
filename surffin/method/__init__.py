"""The method: numpy kernels under xarray functions, one module per step, and the stages that chain them."""
