// PCL's cylinder pipeline on one cloud, for bench/bench_pcl.py (our harness, PCL 1.13 API;
// bench_pcl.py compiles it with g++ and pkg-config's flags for libpcl-dev):
// k = 50 neighbourhood normals, removal of the dominant plane (SACSegmentationFromNormals,
// SACMODEL_NORMAL_PLANE), then SACSegmentationFromNormals with SACMODEL_CYLINDER on the rest.
// Reads "x y z" lines (metres) from argv[1]; argv[2] is the distance threshold (m), argv[3] and
// argv[4] the radius limits (m), argv[5] the random seed. Prints one line:
// "seconds radius_m inliers ax ay az dx dy dz" (the time covers the pipeline, not the reading).
#include <pcl/ModelCoefficients.h>
#include <pcl/features/normal_3d.h>
#include <pcl/filters/extract_indices.h>
#include <pcl/point_types.h>
#include <pcl/sample_consensus/method_types.h>
#include <pcl/sample_consensus/model_types.h>
#include <pcl/search/kdtree.h>
#include <pcl/segmentation/sac_segmentation.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>

int main(int argc, char** argv) {
  if (argc < 6) {
    std::cerr << "usage: cylinder_pcl CLOUD.xyz THRESHOLD R_MIN R_MAX SEED\n";
    return 2;
  }
  const double threshold = std::atof(argv[2]);
  const double r_min = std::atof(argv[3]);
  const double r_max = std::atof(argv[4]);
  std::srand(static_cast<unsigned>(std::atoi(argv[5])));  // PCL's RANSAC draws with rand()

  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZ>);
  std::ifstream in(argv[1]);
  if (!in) {
    std::cerr << "cannot read " << argv[1] << "\n";
    return 2;
  }
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream ss(line);
    pcl::PointXYZ p;
    if (ss >> p.x >> p.y >> p.z) cloud->push_back(p);
  }

  const auto t0 = std::chrono::steady_clock::now();
  pcl::search::KdTree<pcl::PointXYZ>::Ptr tree(new pcl::search::KdTree<pcl::PointXYZ>());
  pcl::NormalEstimation<pcl::PointXYZ, pcl::Normal> ne;
  pcl::PointCloud<pcl::Normal>::Ptr normals(new pcl::PointCloud<pcl::Normal>);
  ne.setSearchMethod(tree);
  ne.setInputCloud(cloud);
  ne.setKSearch(50);
  ne.compute(*normals);

  // the dominant plane (the table)
  pcl::SACSegmentationFromNormals<pcl::PointXYZ, pcl::Normal> seg;
  pcl::PointIndices::Ptr plane_inliers(new pcl::PointIndices);
  pcl::ModelCoefficients::Ptr plane(new pcl::ModelCoefficients);
  seg.setOptimizeCoefficients(true);
  seg.setModelType(pcl::SACMODEL_NORMAL_PLANE);
  seg.setNormalDistanceWeight(0.1);
  seg.setMethodType(pcl::SAC_RANSAC);
  seg.setMaxIterations(100);
  seg.setDistanceThreshold(threshold);
  seg.setInputCloud(cloud);
  seg.setInputNormals(normals);
  seg.segment(*plane_inliers, *plane);

  pcl::PointCloud<pcl::PointXYZ>::Ptr rest(new pcl::PointCloud<pcl::PointXYZ>);
  pcl::PointCloud<pcl::Normal>::Ptr rest_normals(new pcl::PointCloud<pcl::Normal>);
  pcl::ExtractIndices<pcl::PointXYZ> extract;
  extract.setInputCloud(cloud);
  extract.setIndices(plane_inliers);
  extract.setNegative(true);
  extract.filter(*rest);
  pcl::ExtractIndices<pcl::Normal> extract_normals;
  extract_normals.setInputCloud(normals);
  extract_normals.setIndices(plane_inliers);
  extract_normals.setNegative(true);
  extract_normals.filter(*rest_normals);

  // the cylinder
  pcl::PointIndices::Ptr cyl_inliers(new pcl::PointIndices);
  pcl::ModelCoefficients::Ptr cyl(new pcl::ModelCoefficients);
  seg.setOptimizeCoefficients(true);
  seg.setModelType(pcl::SACMODEL_CYLINDER);
  seg.setMethodType(pcl::SAC_RANSAC);
  seg.setNormalDistanceWeight(0.1);
  seg.setMaxIterations(10000);
  seg.setDistanceThreshold(threshold);
  seg.setRadiusLimits(r_min, r_max);
  seg.setInputCloud(rest);
  seg.setInputNormals(rest_normals);
  seg.segment(*cyl_inliers, *cyl);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  if (cyl->values.size() < 7) {
    std::printf("%.6f nan 0 nan nan nan nan nan nan\n", seconds);
    return 0;
  }
  const auto& v = cyl->values;
  std::printf("%.6f %.9f %zu %.9f %.9f %.9f %.9f %.9f %.9f\n", seconds, v[6], cyl_inliers->indices.size(), v[0], v[1],
              v[2], v[3], v[4], v[5]);
  return 0;
}
