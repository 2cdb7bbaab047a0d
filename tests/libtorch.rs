//! The libtorch set-up works: this test executable finds libtorch through its rpath (no
//! LD_LIBRARY_PATH), runs a forward and a backward pass on the CPU, and autograd's gradient
//! equals the closed form.

use tch::{Kind, Tensor};

/// A linear layer y = W x + b under the loss L = mean_i sum_j (y_ij - t_ij)^2 has
/// dL/dW = (2/n) (Y - T)^T X and dL/db = (2/n) sum_i (y_i - t_i).
#[test]
fn linear_layer_gradient_matches_closed_form() {
    let n = 4;
    let x = Tensor::from_slice(&[0.5, -1.0, 2.0, 0.25, -0.75, 1.5, 3.0, -2.0]).view([n, 2]);
    let t = Tensor::from_slice(&[
        1.0, 0.0, -1.0, 2.0, 0.5, -0.5, 0.0, 1.0, 2.0, -2.0, 1.0, 0.0,
    ])
    .view([n, 3]);
    let w = Tensor::from_slice(&[0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
        .view([3, 2])
        .set_requires_grad(true);
    let b = Tensor::from_slice(&[0.05, -0.05, 0.1]).set_requires_grad(true);

    let y = x.matmul(&w.tr()) + &b;
    let loss = (&y - &t)
        .square()
        .sum_dim_intlist(1, false, Kind::Double)
        .mean(Kind::Double);
    loss.backward();

    let residual = (&y - &t).detach();
    let expected_w = residual.tr().matmul(&x) * (2.0 / n as f64);
    let expected_b = residual.sum_dim_intlist(0, false, Kind::Double) * (2.0 / n as f64);
    let err_w = (w.grad() - &expected_w).abs().max().double_value(&[]);
    let err_b = (b.grad() - &expected_b).abs().max().double_value(&[]);
    assert!(
        err_w < 1e-12,
        "dL/dW differs from the closed form by {err_w}"
    );
    assert!(
        err_b < 1e-12,
        "dL/db differs from the closed form by {err_b}"
    );
    // The gradient is not trivially zero: the check above would pass vacuously otherwise.
    assert!(expected_w.abs().sum(Kind::Double).double_value(&[]) > 1.0);
}
