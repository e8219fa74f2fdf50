//! Adam (Kingma & Ba, 2015), maximising, with a learning rate per coordinate.

/// Adam state over a flat parameter vector.
#[derive(Debug, Clone)]
pub struct Adam {
    m: Vec<f64>,
    v: Vec<f64>,
    t: i32,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

impl Adam {
    pub fn new(n: usize) -> Self {
        Adam { m: vec![0.0; n], v: vec![0.0; n], t: 0, beta1: 0.9, beta2: 0.999, eps: 1e-8 }
    }

    /// One ascent step: `theta += scale * lr * m_hat / (sqrt(v_hat) + eps)`.
    pub fn step(&mut self, theta: &mut [f64], grad: &[f64], lr: &[f64], scale: f64) {
        self.t += 1;
        let (b1t, b2t) = (1.0 - self.beta1.powi(self.t), 1.0 - self.beta2.powi(self.t));
        for i in 0..theta.len() {
            let g = if grad[i].is_finite() { grad[i] } else { 0.0 };
            self.m[i] = self.beta1 * self.m[i] + (1.0 - self.beta1) * g;
            self.v[i] = self.beta2 * self.v[i] + (1.0 - self.beta2) * g * g;
            theta[i] += scale * lr[i] * (self.m[i] / b1t) / ((self.v[i] / b2t).sqrt() + self.eps);
        }
    }
}
