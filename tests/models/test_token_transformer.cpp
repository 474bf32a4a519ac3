// Token transformer (adapter hooks, padding, text condition) and the TMD / masking
// maths of the token priors: path probabilities, beta, mask-count schedules.
#include <catch2/catch.hpp>

#include <cmath>

#include "core/error.h"
#include "models/token_prior.h"
#include "models/token_transformer.h"

using namespace mc;

namespace {

// d(i, j) = (2 - 2 cos(e_i, e_j))^2 of a random codebook, as the tokenizer builds it.
torch::Tensor random_distance(int64_t K, int64_t D, uint64_t seed) {
  torch::manual_seed(seed);
  auto e = torch::nn::functional::normalize(torch::randn({K, D}, torch::kFloat64),
                                            torch::nn::functional::NormalizeFuncOptions().dim(1));
  auto d = (2.0 - 2.0 * torch::matmul(e, e.t()).clamp(-1.0, 1.0)).pow(2);
  d.fill_diagonal_(0.0);
  return d;
}

TokenTransformerOptions tiny_options(bool use_time = true) {
  TokenTransformerOptions o;
  o.num_codes = 16;
  o.depth = 3;
  o.width = 32;
  o.heads = 4;
  o.dropout = 0.0;
  o.text_dim = 24;
  o.freq_dim = 16;
  o.use_time = use_time;
  return o;
}

// An untrained network is the identity in every block (AdaLN-Zero) and has zero logits:
// random weights make the hooks' effect visible.
TokenTransformer randomised(const TokenTransformerOptions& o, uint64_t seed) {
  torch::manual_seed(seed);
  TokenTransformer net(o);
  torch::NoGradGuard ng;
  for (auto& p : net->parameters()) p.normal_(0.0, 0.2);
  net->eval();
  return net;
}

TextContext random_text(int64_t B, int64_t W, int64_t dim, uint64_t seed) {
  torch::manual_seed(seed);
  TextContext c;
  c.pooled = torch::randn({B, dim});
  c.memory = torch::randn({B, W, dim});
  c.memory_valid = torch::ones({B, W}, torch::kBool);
  c.memory_valid[1].narrow(0, 3, W - 3).fill_(false);
  return c;
}

}  // namespace

TEST_CASE("TMD path: q_t is uniform at t = 0 and concentrates on x1 as t -> 1", "[tmd]") {
  const int64_t K = 24;
  auto dist = random_distance(K, 6, 3);
  auto x1 = torch::tensor({0, 5, 23}, torch::kInt64);
  auto q0 = tmd_path_probs(dist, x1, tmd_beta(torch::zeros({3}, torch::kFloat64), 3.0, 0.9));
  CHECK(torch::allclose(q0, torch::full({3, K}, 1.0 / K, torch::kFloat64), 0, 1e-12));
  double prev = 1.0 / K;
  for (double t : {0.2, 0.5, 0.8, 0.95, 0.99, 0.9999}) {
    auto beta = tmd_beta(torch::full({3}, t, torch::kFloat64), 3.0, 0.9);
    auto q = tmd_path_probs(dist, x1, beta);
    CHECK(torch::allclose(q.sum(-1), torch::ones({3}, torch::kFloat64), 0, 1e-12));
    double at_x1 = q.gather(-1, x1.unsqueeze(-1)).min().item<double>();
    CHECK(at_x1 > prev);  // the clean token's mass grows with t
    prev = at_x1;
  }
  CHECK(prev > 0.999);
  // q_t(i | x1) orders tokens by their distance to x1.
  auto q = tmd_path_probs(dist, x1, torch::full({3}, 2.0, torch::kFloat64));
  auto order_q = q[1].argsort(int64_t{0}, true), order_d = dist[5].argsort(int64_t{0}, false);
  CHECK(torch::equal(order_q.narrow(0, 0, 5), order_d.narrow(0, 0, 5)));
}

TEST_CASE("TMD beta: closed form and beta' against a finite difference", "[tmd]") {
  const double c = 3.0, a = 0.9;
  auto b = tmd_beta(torch::tensor({0.0, 0.5, 0.75}, torch::kFloat64), c, a);
  CHECK(b[0].item<double>() == 0.0);
  CHECK(b[1].item<double>() == Approx(3.0));                       // t / (1 - t) = 1
  CHECK(b[2].item<double>() == Approx(3.0 * std::pow(3.0, 0.9)));  // t / (1 - t) = 3
  for (double t : {0.05, 0.2, 0.5, 0.8, 0.97}) {
    const double h = 1e-6;
    double fd = (tmd_beta(torch::tensor(t + h, torch::kFloat64), c, a).item<double>() -
                 tmd_beta(torch::tensor(t - h, torch::kFloat64), c, a).item<double>()) /
                (2 * h);
    CHECK(tmd_beta_prime(torch::tensor(t, torch::kFloat64), c, a).item<double>() == Approx(fd).epsilon(1e-6));
  }
  // Other (c, a): a = 1 gives beta' = c / (1 - t)^2.
  CHECK(tmd_beta_prime(torch::tensor(0.5, torch::kFloat64), 2.0, 1.0).item<double>() == Approx(8.0));
}

TEST_CASE("masking schedules: cosine counts, at least one token", "[tmd]") {
  CHECK(masked_train_count(10, 0.0) == 10);
  CHECK(masked_train_count(10, 0.5) == 7);   // round(10 cos(pi/4)) = round(7.07)
  CHECK(masked_train_count(10, 1.0) == 1);   // cos(pi/2) = 0, but never zero
  CHECK(masked_train_count(49, 2.0 / 3.0) == 25);  // round(49 * 0.5) = round(24.5)
  CHECK(masked_train_count(1, 0.3) == 1);
  for (int64_t n : {1, 7, 49}) {
    CHECK(masked_sample_count(n, 0, 10) == n);  // step 0: everything masked
    CHECK(masked_sample_count(n, 9, 10) == 1);  // last step: one token re-predicted
    int64_t prev = n;
    for (int k = 0; k < 10; ++k) {
      int64_t m = masked_sample_count(n, k, 10);
      CHECK(m <= prev);
      CHECK(m >= 1);
      prev = m;
    }
  }
  CHECK(masked_sample_count(20, 0, 1) == 20);  // a single step predicts all
}

TEST_CASE("token transformer: extra KV with zero-length or fully masked memory changes nothing", "[tmd]") {
  auto o = tiny_options();
  auto net = randomised(o, 7);
  const int64_t B = 2, L = 9, W = 6, d = o.width;
  torch::manual_seed(8);
  auto ids = torch::randint(0, o.num_codes + 1, {B, L}, torch::kInt64);
  auto valid = torch::ones({B, L}, torch::kBool);
  valid[1].narrow(0, 6, 3).fill_(false);
  auto t = torch::tensor({0.3f, 0.8f});
  auto text = random_text(B, W, o.text_dim, 9);
  torch::NoGradGuard ng;
  auto base = net->forward(ids, t, text, valid).logits;
  REQUIRE(base.sizes().vec() == std::vector<int64_t>{B, L, o.num_codes});
  CHECK(base.abs().max().item<double>() > 1e-3);

  TokenTransformerHooks empty;
  for (int l = 0; l < o.depth; ++l) empty.extra_kv.push_back({torch::zeros({B, 0, d}), torch::zeros({B, 0, d}), {}});
  CHECK(torch::allclose(net->forward(ids, t, text, valid, &empty).logits, base, 1e-5, 1e-6));

  TokenTransformerHooks masked, live;
  for (int l = 0; l < o.depth; ++l) {
    auto k = torch::randn({B, 4, d}) * 3, v = torch::randn({B, 4, d}) * 3;
    masked.extra_kv.push_back({k, v, torch::zeros({B, 4}, torch::kBool)});
    live.extra_kv.push_back({k, v, {}});
  }
  CHECK(torch::allclose(net->forward(ids, t, text, valid, &masked).logits, base, 1e-5, 1e-6));
  // The hook is live: unmasked memory changes the valid positions' logits.
  auto with_kv = net->forward(ids, t, text, valid, &live).logits;
  CHECK((with_kv - base).abs().max().item<double>() > 1e-3);
  // Per-sample masks: row 0 sees nothing extra, row 1 does.
  TokenTransformerHooks half = live;
  for (auto& kv : half.extra_kv) {
    kv.mask = torch::ones({B, 4}, torch::kBool);
    kv.mask[0].fill_(false);
  }
  auto h = net->forward(ids, t, text, valid, &half).logits;
  CHECK(torch::allclose(h[0], base[0], 1e-5, 1e-6));
  CHECK(torch::allclose(h[1], with_kv[1], 1e-5, 1e-6));
  // Undefined entries skip a layer; a wrong count is a UserError.
  TokenTransformerHooks skip;
  skip.extra_kv.resize(o.depth);
  CHECK(torch::allclose(net->forward(ids, t, text, valid, &skip).logits, base, 1e-6, 1e-7));
  TokenTransformerHooks wrong;
  wrong.extra_kv.resize(1);
  CHECK_THROWS_AS(net->forward(ids, t, text, valid, &wrong), UserError);
}

TEST_CASE("token transformer: block residual hook and hidden states", "[tmd]") {
  auto o = tiny_options();
  auto net = randomised(o, 11);
  const int64_t B = 2, L = 5, W = 4;
  torch::manual_seed(12);
  auto ids = torch::randint(0, o.num_codes, {B, L}, torch::kInt64);
  auto valid = torch::ones({B, L}, torch::kBool);
  auto t = torch::tensor({0.1f, 0.6f});
  auto text = random_text(B, W, o.text_dim, 13);
  torch::NoGradGuard ng;
  TokenTransformerHooks collect;
  collect.collect_hidden = true;
  auto out = net->forward(ids, t, text, valid, &collect);
  REQUIRE(out.hidden.size() == static_cast<size_t>(o.depth));
  CHECK(out.hidden[0].sizes().vec() == std::vector<int64_t>{B, L, o.width});
  TokenTransformerHooks zero = collect;
  for (int l = 0; l < o.depth; ++l) zero.block_residuals.push_back(torch::zeros({B, L, o.width}));
  CHECK(torch::allclose(net->forward(ids, t, text, valid, &zero).logits, out.logits, 1e-6, 1e-7));
  // A residual after the last block shifts its hidden state by exactly that amount.
  TokenTransformerHooks last = collect;
  last.block_residuals.resize(o.depth);
  auto r = torch::randn({B, L, o.width});
  last.block_residuals.back() = r;
  auto shifted = net->forward(ids, t, text, valid, &last);
  CHECK(torch::allclose(shifted.hidden.back(), out.hidden.back() + r, 1e-5, 1e-6));
  CHECK(torch::allclose(shifted.hidden.front(), out.hidden.front(), 1e-6, 1e-7));
  CHECK_FALSE(torch::allclose(shifted.logits, out.logits, 1e-4, 1e-4));
}

TEST_CASE("token transformer: padding, text memory and time all matter where they should", "[tmd]") {
  auto o = tiny_options();
  auto net = randomised(o, 21);
  const int64_t B = 2, L = 8, W = 5;
  torch::manual_seed(22);
  auto ids = torch::randint(0, o.num_codes, {B, L}, torch::kInt64);
  auto valid = torch::ones({B, L}, torch::kBool);
  valid[0].narrow(0, 5, 3).fill_(false);
  auto t = torch::tensor({0.4f, 0.4f});
  auto text = random_text(B, W, o.text_dim, 23);
  torch::NoGradGuard ng;
  auto base = net->forward(ids, t, text, valid).logits;
  // Padded ids do not reach valid positions.
  auto ids2 = ids.clone();
  ids2[0].narrow(0, 5, 3).fill_(o.num_codes);
  CHECK(torch::allclose(net->forward(ids2, t, text, valid).logits[0].narrow(0, 0, 5), base[0].narrow(0, 0, 5), 1e-5,
                        1e-6));
  // Masked-out words of the memory do not matter; real ones do.
  auto text2 = text;
  text2.memory = text.memory.clone();
  text2.memory[1].narrow(0, 3, W - 3).normal_();
  CHECK(torch::allclose(net->forward(ids, t, text2, valid).logits, base, 1e-5, 1e-6));
  text2.memory[1][0].normal_();
  CHECK_FALSE(torch::allclose(net->forward(ids, t, text2, valid).logits[1], base[1], 1e-4, 1e-4));
  CHECK_FALSE(torch::allclose(net->forward(ids, torch::tensor({0.9f, 0.9f}), text, valid).logits, base, 1e-4, 1e-4));
  // The masked baseline's network takes no time at all.
  auto untimed = randomised(tiny_options(false), 24);
  CHECK(untimed->forward(ids, torch::Tensor(), text, valid).logits.size(2) == o.num_codes);
  CHECK_THROWS_AS(net->forward(ids, torch::Tensor(), text, valid), UserError);
}

TEST_CASE("token prior net: condition dropout swaps in the null context", "[tmd]") {
  TmdPriorConfig c;
  c.depth = 2;
  c.width = 32;
  c.heads = 2;
  c.text_width = 16;
  c.text_heads = 2;
  c.text_ff = 32;
  c.text_layers = 1;
  c.max_words = 8;
  TokenPriorNet net(10, 12, c);
  net->eval();
  torch::NoGradGuard ng;
  auto ids = torch::tensor({{2, 4, 5, 3, 0, 0, 0, 0}, {2, 6, 3, 0, 0, 0, 0, 0}}, torch::kInt64);
  auto text = net->encode_text(ids, torch::tensor({4, 3}, torch::kInt64));
  CHECK(text.memory.sizes().vec() == std::vector<int64_t>{2, 8, 16});
  CHECK(text.memory_valid.sum().item<int64_t>() == 7);
  auto dropped = net->drop_condition(text, torch::tensor({false, true}));
  auto null = net->null_context(2, 8);
  CHECK(torch::equal(dropped.pooled[0], text.pooled[0]));
  CHECK(torch::equal(dropped.pooled[1], null.pooled[1]));
  CHECK(torch::equal(dropped.memory[1], null.memory[1]));
  CHECK(dropped.memory_valid[1].sum().item<int64_t>() == 1);
  CHECK(torch::equal(dropped.memory_valid[0], text.memory_valid[0]));
}
