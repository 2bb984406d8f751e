use candle_core::{Device, Tensor, D};
use drivescript::io::{load_scene, LoadOptions};
use drivescript::train::{build, load, windows, Window};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let t = load(std::path::Path::new(&args[1])).unwrap();
    let cfg = t.meta.config.window;
    let mut ws: Vec<Window> = Vec::new();
    for f in &args[2..] {
        let s = load_scene(std::path::Path::new(f), 0, &LoadOptions::default()).unwrap();
        ws.extend(windows(&s, &cfg));
    }
    let refs: Vec<&Window> = ws.iter().take(8).collect();
    let b = build(&refs, &cfg, &t.meta.normaliser, &Device::Cpu).unwrap();
    let map = t.model.encode_map(&b.ctx).unwrap();
    let n = refs.len();
    for sigma in [0.002, 0.01, 0.05, 0.2, 0.5, 1.0, 2.0, 5.0, 20.0, 80.0] {
        let noise = Tensor::randn(0f32, 1.0, b.target.shape(), &Device::Cpu).unwrap();
        let x = (&b.target + (noise * sigma).unwrap()).unwrap();
        let d = t.model.denoise(&b.ctx, &map, &x, &vec![sigma; n]).unwrap();
        let err = |y: &Tensor| -> f32 {
            let e = (y - &b.target)
                .unwrap()
                .sqr()
                .unwrap()
                .sum(D::Minus1)
                .unwrap();
            let m = (e * &b.loss_mask)
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap();
            m / b.loss_mask.sum_all().unwrap().to_scalar::<f32>().unwrap()
        };
        let zero = (&b.target * 0.0).unwrap();
        println!(
            "sigma {sigma:>6}: |D-y|^2 {:.5}  |x-y|^2 {:.5}  |0-y|^2 {:.5}",
            err(&d),
            err(&x),
            err(&zero)
        );
    }
}
