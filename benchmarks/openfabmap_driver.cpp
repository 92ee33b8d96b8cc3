// Times openFABMAP 2.0 (of2::FabMap2, https://github.com/arrenglover/openfabmap) per query on
// words given by topoloc, for the side-by-side speed rows of benchmarks/bench_fabmap_speed.py.
// Only this driver is kept in topoloc; openFABMAP's own sources are compiled beside it at
// benchmark time (benchmarks/openfabmap.py) and never copied into the repository.
//
// Input (text, whitespace separated):
//   V p_ge p_gne reps
//   4 rows of V numbers: the Chow-Liu tree in openFABMAP's layout (parent, p(z), p(z|z_p=1), p(z|z_p=0))
//   n_train, then per image: k and its k word ids      (sampled places of the new-place term)
//   n_map, then per image as above                     (the map: one location per image)
//   n_query, then per image as above
// Output (text, one line per query): ms best_image log_likelihood_best p_new p_best; with a third
// argument, also every map image's log-likelihood (relative to the empty place), one line per query
//   ms: the fastest of `reps` timed FabMap2::localize calls on that query (new-place term, every
//   map location's likelihood, normalisation and smoothing); the query's dense descriptor, the
//   input format openFABMAP takes, is built before the clock starts.
#include <chrono>
#include <fstream>
#include <iostream>
#include <limits>
#include <vector>

#include "fabmap.hpp"

static std::vector<cv::Mat> read_images(std::istream& in, int v) {
    int n = 0;
    in >> n;
    std::vector<cv::Mat> out;
    out.reserve(n);
    for (int i = 0; i < n; i++) {
        int k = 0;
        in >> k;
        cv::Mat d = cv::Mat::zeros(1, v, CV_32F);
        for (int j = 0; j < k; j++) {
            int w = 0;
            in >> w;
            d.at<float>(0, w) = 1.0f;
        }
        out.push_back(d);
    }
    return out;
}

int main(int argc, char** argv) {
    if (argc != 3 && argc != 4) {
        std::cerr << "usage: openfabmap_driver INPUT OUTPUT [LIKELIHOODS]\n";
        return 2;
    }
    std::ifstream in(argv[1]);
    int v = 0, reps = 1;
    double p_ge = 0.0, p_gne = 0.0;
    if (!(in >> v >> p_ge >> p_gne >> reps) || v <= 0 || reps <= 0) {
        std::cerr << "openfabmap_driver: bad header in " << argv[1] << "\n";
        return 2;
    }
    cv::Mat tree(4, v, CV_64F);
    for (int r = 0; r < 4; r++)
        for (int q = 0; q < v; q++) in >> tree.at<double>(r, q);
    std::vector<cv::Mat> training = read_images(in, v);
    std::vector<cv::Mat> map = read_images(in, v);
    std::vector<cv::Mat> queries = read_images(in, v);
    if (!in || training.empty() || map.empty() || queries.empty()) {
        std::cerr << "openfabmap_driver: truncated input " << argv[1] << "\n";
        return 2;
    }
    of2::FabMap2 fabmap(tree, p_ge, p_gne, of2::FabMap::SAMPLED | of2::FabMap::CHOW_LIU);
    fabmap.addTraining(training);
    fabmap.add(map);
    {  // warm-up outside the timings, as topoloc's side does
        std::vector<of2::IMatch> warm;
        fabmap.localize(queries[0], warm, false);
    }
    std::ofstream out(argv[2]);
    out.precision(17);
    std::ofstream lik;
    if (argc == 4) {
        lik.open(argv[3]);
        lik.precision(17);
    }
    for (size_t i = 0; i < queries.size(); i++) {
        double best_ms = std::numeric_limits<double>::infinity();
        std::vector<of2::IMatch> matches;
        for (int r = 0; r < reps; r++) {
            matches.clear();
            auto t0 = std::chrono::steady_clock::now();
            fabmap.localize(queries[i], matches, false);
            auto t1 = std::chrono::steady_clock::now();
            double ms = std::chrono::duration<double, std::milli>(t1 - t0).count();
            if (ms < best_ms) best_ms = ms;
        }
        if (argc == 4) {
            std::vector<double> row(map.size(), 0.0);
            for (const of2::IMatch& m : matches)
                if (m.imgIdx >= 0) row[m.imgIdx] = m.likelihood;
            for (size_t j = 0; j < row.size(); j++) lik << (j ? " " : "") << row[j];
            lik << "\n";
        }
        int best = -1;
        double best_ll = -std::numeric_limits<double>::infinity(), p_new = 0.0, p_best = 0.0;
        for (const of2::IMatch& m : matches) {
            if (m.imgIdx < 0) {
                p_new = m.match;
            } else if (m.likelihood > best_ll) {
                best_ll = m.likelihood;
                best = m.imgIdx;
                p_best = m.match;
            }
        }
        out << best_ms << " " << best << " " << best_ll << " " << p_new << " " << p_best << "\n";
    }
    return 0;
}
